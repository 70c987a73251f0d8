"""Execute a pick-and-place plan (plan.json from `normpos-grasp plan`) on an `ArmDriver`; dry run by default.

plan.json fields used here: `status` ("ok" or a reason), `robot` (UR model), `world_from_base` (4x4),
`joint_waypoints` (ordered `[{name, q}]`, rad), optional `trajectory` (time-stamped joint samples:
`{"samples": [{t, q}, ...]}` as `normpos-grasp plan` writes it, a list of `{t, q}`, or
`{"t": [...], "q": [[...]]}`), `tool` (`flange_from_tcp` 4x4). Everything is checked against the limits before
the first command; a plan that fails any check is never sent.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.cell.stream import waypoint_samples
from normpos_grasp.errors import DriverFault, InputError, SafetyViolation
from normpos_grasp.records.plan import PLAN_FORMAT
from normpos_grasp.typing import FloatArray
from normpos_grasp.validation import as_float_array, check_pose, short_repr

from .driver import ArmDriver, GuardedDriver
from .gripper_config import ArmIOGripper, ToolDriver, arm_watch
from .safety import SafetyLimits

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExecuteOptions:
    """How a plan is run. speed (rad/s) and accel (rad/s^2): movej caps between waypoints when the plan has no
    trajectory (and for the approach to its first waypoint). close_at / open_at: waypoint names after which the
    gripper closes / opens. start_tol_rad: farther than this from the first waypoint, the arm first moves there.
    final_tol_rad: the executed plan must end this close to its last waypoint (else DriverFault). hold_at_end: where
    the plan runs in one stream, leave it open at the end, holding the arm there, so that the next plan (starting
    there) goes on in it (the caller ends it otherwise: `GuardedDriver.end_stream`)."""

    speed: float = 0.8
    accel: float = 1.2
    close_at: tuple[str, ...] = ("grasp",)
    open_at: tuple[str, ...] = ("place",)
    open_first: bool = True
    start_tol_rad: float = 1e-3
    final_tol_rad: float = 1e-3
    check_grip: bool = True
    hold_at_end: bool = False


@dataclass(frozen=True)
class ParsedPlan:
    """The parts of plan.json execution needs. names: waypoint names; q: (N, 6) rad; traj_t: (M,) s, traj_q: (M, 6)."""

    robot: str
    names: tuple[str, ...]
    q: FloatArray
    traj_t: FloatArray | None
    traj_q: FloatArray | None
    flange_from_tcp: FloatArray | None
    world_from_base: FloatArray


@dataclass(frozen=True)
class StepRecord:
    name: str
    kind: str  # "approach", "trajectory", "movej", "gripper_close", "gripper_open"
    duration_s: float
    error_rad: float = 0.0


@dataclass(frozen=True)
class ExecutionReport:
    """Outcome of `execute_plan`. status: "dry_run" (checked, nothing sent), "executed", or "grip_failed" (the
    grip-detect input stayed low after closing: the pick stopped at the grasp, the arm at rest; a result to act on).

    final_q: (6,) joints at the end (None in a dry run without state). final_error_rad: max joint error to the
    plan's last waypoint. grip_detected: the grip-detect input after closing (None when not configured/checked).
    """

    status: str
    steps: tuple[StepRecord, ...] = ()
    final_q: FloatArray | None = None
    final_error_rad: float | None = None
    grip_detected: bool | None = None
    commands_sent: int = 0
    messages: tuple[str, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict[str, Any]:
        return {
            "status": self.status,
            "steps": [s.__dict__ for s in self.steps],
            "final_q": None if self.final_q is None else self.final_q.tolist(),
            "final_error_rad": self.final_error_rad,
            "grip_detected": self.grip_detected,
            "commands_sent": self.commands_sent,
            "messages": list(self.messages),
        }


def load_plan(path: str | Path) -> dict[str, Any]:
    """Read plan.json; InputError if it is missing or not JSON."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputError(f"plan file {p} does not exist; create it with `normpos-grasp plan`") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"plan file {p} is not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise InputError(f"plan file {p}: expected a JSON object, got {type(data).__name__}")
    return data


def parse_plan(plan: dict[str, Any]) -> ParsedPlan:
    """Validate the fields execution needs; InputError naming the bad field. A plan without `format` (written by
    hand or by another tool) is read by its fields; one that names another format, or another version of this one,
    is refused."""
    fmt = plan.get("format")
    if fmt is not None and fmt != PLAN_FORMAT:
        raise InputError(
            f"plan.format: {short_repr(fmt)} is not this version's plan format {PLAN_FORMAT!r}; re-plan with "
            "`normpos-grasp plan`"
        )
    status = plan.get("status")
    if status != "ok":
        raise InputError(f"plan status is {status!r}, not 'ok': there is nothing to execute (see its candidates)")
    robot = plan.get("robot")
    if isinstance(robot, dict):
        robot = robot.get("model", robot.get("name"))
    if not isinstance(robot, str):
        raise InputError(f"plan.robot: expected a UR model name, got {robot!r}")
    wps = plan.get("joint_waypoints")
    if not isinstance(wps, list) or not wps:
        raise InputError("plan.joint_waypoints: expected a non-empty list of {name, q}")
    names: list[str] = []
    qs: list[FloatArray] = []
    for i, wp in enumerate(wps):
        if not isinstance(wp, dict) or "q" not in wp:
            raise InputError(f"plan.joint_waypoints[{i}]: expected {{name, q}}, got {wp!r}")
        names.append(str(wp.get("name", f"waypoint_{i}")))
        qs.append(as_float_array(wp["q"], f"plan.joint_waypoints[{i}].q", (6,)))
    traj_t = traj_q = None
    traj = plan.get("trajectory")
    if traj:
        if isinstance(traj, dict) and isinstance(traj.get("samples"), list):
            traj = traj["samples"]  # normpos-grasp plan: {dt_s, duration_s, samples: [{t, q}]}
        if isinstance(traj, dict):
            t_raw = traj.get("t", traj.get("times", traj.get("time_s")))
            q_raw = traj.get("q", traj.get("positions"))
        elif isinstance(traj, list):
            t_raw = [s.get("t", s.get("time_s")) for s in traj]
            q_raw = [s.get("q") for s in traj]
        else:
            raise InputError(
                f"plan.trajectory: expected a list of {{t, q}} or {{t: [...], q: [...]}}, got {type(traj)}"
            )
        if t_raw is None or q_raw is None:
            raise InputError("plan.trajectory: needs time stamps ('t') and joint samples ('q')")
        traj_t = as_float_array(t_raw, "plan.trajectory.t", (None,))
        traj_q = as_float_array(q_raw, "plan.trajectory.q", (traj_t.shape[0], 6))
    tool = plan.get("tool") or {}
    if not isinstance(tool, dict):
        raise InputError(f"plan.tool: expected a mapping, got {short_repr(tool)}")
    for key in ("opening_m", "stroke_m"):
        if key in tool:
            _metres(tool[key], f"plan.tool.{key}")
    opening = _grasp_opening(plan)
    stroke = tool.get("stroke_m")
    if opening is not None and stroke is not None and float(stroke) > 0.0 and opening > float(stroke) + 1e-6:
        raise InputError(
            f"plan: the grasp opening {opening * 1000:.1f} mm is more than the tool's stroke "
            f"{float(stroke) * 1000:.1f} mm (plan.tool.stroke_m)"
        )
    flange_from_tcp = (
        check_pose(tool["flange_from_tcp"], "plan.tool.flange_from_tcp") if "flange_from_tcp" in tool else None
    )
    wfb = check_pose(plan.get("world_from_base", np.eye(4)), "plan.world_from_base")
    return ParsedPlan(robot.lower(), tuple(names), np.stack(qs), traj_t, traj_q, flange_from_tcp, wfb)


def check_plan(parsed: ParsedPlan, limits: SafetyLimits) -> SafetyLimits:
    """Check every waypoint, every joint segment and the trajectory; returns the limits used.

    With a cell's limits (`SafetyLimits.cell`) the cell is the judge: the plan's tool must be the mounted one and
    its world_from_base the arm's mount (a plan can never swap in a shorter tool to pass the workspace check).
    With a bare arm's limits the plan's tool is the only one known and is used for the workspace check.
    Raises SafetyViolation (nothing sent) or InputError (plan for another robot)."""
    if parsed.robot != limits.model:
        raise InputError(f"plan is for {parsed.robot!r} but the limits are for {limits.model!r}; wrong robot?")
    if limits.cell:
        if parsed.flange_from_tcp is not None and not np.allclose(
            parsed.flange_from_tcp, limits.flange_from_tcp, atol=1e-6
        ):
            raise SafetyViolation(
                f"the plan's tool (flange_from_tcp) is not the tool mounted in cell {limits.cell!r}: re-plan in this "
                "cell; nothing was sent"
            )
        if not np.allclose(parsed.world_from_base, limits.box_from_base, atol=1e-6):
            raise SafetyViolation(
                f"the plan's world_from_base is not the arm's mount in cell {limits.cell!r}: re-plan in this cell; "
                "nothing was sent"
            )
    elif parsed.flange_from_tcp is not None:
        limits = replace(limits, flange_from_tcp=parsed.flange_from_tcp)
    limits.check_path(parsed.names, parsed.q, parsed.traj_t, parsed.traj_q)  # the planner runs the same judge
    return limits


def _split_trajectory(parsed: ParsedPlan) -> list[tuple[FloatArray, FloatArray]]:
    """Trajectory slices between consecutive waypoints (matched in order to their nearest samples)."""
    assert parsed.traj_t is not None and parsed.traj_q is not None
    idx, gap = waypoint_samples(parsed.traj_q, parsed.q)
    for k in range(1, len(parsed.q)):
        if gap[k] > 1e-3:
            raise SafetyViolation(
                f"trajectory does not pass through waypoint {parsed.names[k]!r} (closest sample "
                f"{gap[k]:.4f} rad away); the plan is inconsistent, nothing was sent"
            )
    return [(parsed.traj_t[a : b + 1], parsed.traj_q[a : b + 1]) for a, b in zip(idx[:-1], idx[1:], strict=True)]


def _metres(value: Any, what: str) -> float:
    """A jaw opening or stroke in [0, 2) m; InputError naming `what` otherwise (NaN, inf, text, negative)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= float(value) < 2.0:
        raise InputError(f"{what}: expected a length in metres in [0, 2), got {short_repr(value)}")
    return float(value)


def _grasp_opening(plan: dict[str, Any]) -> float | None:
    """The plan's jaw opening before closing (`grasp.opening_m`, else `tool.opening_m`), m; None when absent or 0
    (a suction grasp)."""
    for key in ("grasp", "tool"):
        entry = plan.get(key)
        if isinstance(entry, dict) and "opening_m" in entry:
            value = _metres(entry["opening_m"], f"plan.{key}.opening_m")
            return value if value > 0 else None
    return None


def execute_plan(
    driver: ArmDriver | None,
    plan: dict[str, Any],
    limits: SafetyLimits,
    dry_run: bool = True,
    options: ExecuteOptions | None = None,
    gripper: ToolDriver | None = None,
) -> ExecutionReport:
    """Check `plan` against `limits` and, unless `dry_run`, run it on `driver` (connected).

    gripper: the cell's gripper driver (connected; execution.gripper_config): it opens to the plan's grasp opening
    (`grasp.opening_m`) before the approach and at the place, closes at the grasp and reports the grip; None: the
    arm driver's digital outputs and its grip-detect input. The whole plan is checked before the first command.
    Faults raise the driver's typed DriverFault subclass (ProtectiveStop, EmergencyStop, ConnectionLost,
    DriverTimeout, GripperFault) with the arm stopped.

    A timed plan is streamed piece by piece between the gripper's waypoints (the arm rests at each before the
    gripper acts). Where the gripper is switched by the arm driver's own outputs (gripper None or an ArmIOGripper
    on `driver`, a GuardedDriver), the pieces run in one stream (`follow_trajectory(keep_streaming=True)`): the
    stream holds the arm at rest at the grasp and the place while the gripper settles, with no stop and restart of
    the stream between the pieces; it ends at the plan's end (with `options.hold_at_end` it stays open there when the
    plan ran to its end, for the next plan to go on in) or when the pick stops.
    """
    opts = options or ExecuteOptions()
    parsed = parse_plan(plan)
    opening = _grasp_opening(plan)
    used = check_plan(parsed, limits)
    # movej speed / acceleration between waypoints: the options, never above the caps
    speed = min(opts.speed, float(np.min(used.max_joint_speed)))
    accel = min(opts.accel, float(np.min(used.max_joint_accel)))
    used.check_joint_speed(speed, accel)
    segments = _split_trajectory(parsed) if parsed.traj_t is not None else None
    messages = [f"{len(parsed.q)} waypoints: {', '.join(parsed.names)}"]
    if parsed.traj_t is not None:
        span = float(parsed.traj_t[-1] - parsed.traj_t[0])
        messages.append(f"trajectory: {len(parsed.traj_t)} samples over {span:.2f} s")
    if dry_run:
        return ExecutionReport("dry_run", messages=(*messages, "dry run: nothing was sent"))
    if driver is None:
        raise InputError("execute_plan(dry_run=False) needs a connected driver")
    if parsed.flange_from_tcp is not None and not np.allclose(used.flange_from_tcp, driver.limits.flange_from_tcp):
        driver.limits = replace(driver.limits, flange_from_tcp=used.flange_from_tcp)
    steps: list[StepRecord] = []
    sent0 = getattr(driver, "commands_sent", 0)
    start = driver.state()
    if float(np.max(np.abs(start.q - parsed.q[0]))) > opts.start_tol_rad:
        t0 = time.monotonic()
        st = driver.move_joints(parsed.q[0][None], speed, accel)
        steps.append(
            StepRecord(parsed.names[0], "approach", time.monotonic() - t0, float(np.max(np.abs(st.q - parsed.q[0]))))
        )
    watch = arm_watch(driver)
    if gripper is not None and opening is not None:
        messages.append(f"gripper opening {opening * 1000:.1f} mm (the plan's)")
    if opts.open_first:
        t0 = time.monotonic()
        if gripper is not None:
            gripper.open(opening, watch)
        else:
            driver.gripper_open()
        steps.append(StepRecord(parsed.names[0], "gripper_open", time.monotonic() - t0))
    one_stream = isinstance(driver, GuardedDriver) and (
        gripper is None or (isinstance(gripper, ArmIOGripper) and gripper.arm is driver)
    )
    report: ExecutionReport | None = None
    try:
        report = _run_steps(
            driver, parsed, segments, opts, gripper, opening, watch, (speed, accel), steps, messages, sent0, one_stream
        )
        return report
    finally:
        held = opts.hold_at_end and report is not None and report.status == "executed"
        if one_stream and isinstance(driver, GuardedDriver) and not held:
            driver.end_stream()  # every other way out leaves the stream closed (a no-op after the last piece)


def _run_steps(
    driver: ArmDriver,
    parsed: ParsedPlan,
    segments: list[tuple[FloatArray, FloatArray]] | None,
    opts: ExecuteOptions,
    gripper: ToolDriver | None,
    opening: float | None,
    watch: Any,
    movej: tuple[float, float],
    steps: list[StepRecord],
    messages: list[str],
    sent0: int,
    one_stream: bool,
) -> ExecutionReport:
    """The waypoints of `parsed` after the first: streamed pieces (or movej at `movej` = (speed, accel)), the
    gripper at its waypoints; `one_stream`: the pieces before the last keep the stream open."""
    speed, accel = movej
    grip: bool | None = None
    stream_from = 0  # index of the waypoint the current trajectory stream starts at
    for k in range(1, len(parsed.q)):
        name = parsed.names[k]
        t0 = time.monotonic()
        if segments is not None:
            if name not in opts.close_at and name not in opts.open_at and k < len(parsed.q) - 1:
                continue  # stream on through waypoints without a gripper action
            seg_t = np.concatenate([segments[i][0][(1 if i > stream_from else 0) :] for i in range(stream_from, k)])
            seg_q = np.concatenate([segments[i][1][(1 if i > stream_from else 0) :] for i in range(stream_from, k)])
            stream_from = k
            if len(seg_t) <= 1:
                st = driver.state()
            elif one_stream and (k < len(parsed.q) - 1 or opts.hold_at_end):
                st = driver.follow_trajectory(seg_t, seg_q, keep_streaming=True)
            else:
                st = driver.follow_trajectory(seg_t, seg_q)
            kind = "trajectory"
        else:
            st = driver.move_joints(parsed.q[k][None], speed, accel)
            kind = "movej"
        steps.append(StepRecord(name, kind, time.monotonic() - t0, float(np.max(np.abs(st.q - parsed.q[k])))))
        if name in opts.close_at:
            t0 = time.monotonic()
            if gripper is not None:
                gripper.close(watch)
                detects = gripper.detects_grip
            else:
                driver.gripper_close()
                detects = getattr(getattr(driver, "gripper", None), "grip_detect_input", None) is not None
            steps.append(StepRecord(name, "gripper_close", time.monotonic() - t0))
            if opts.check_grip and detects:
                grip = gripper.grip_detected() if gripper is not None else driver.grip_detected()
                messages.append(f"grip detected: {grip}")
                if not grip:
                    # a missed grip stops the pick here (the arm rests at the grasp): no carrying on to the place
                    messages.append(f"grip not detected after closing at {name!r}: pick stopped, nothing further sent")
                    final = driver.state()
                    return ExecutionReport(
                        "grip_failed",
                        tuple(steps),
                        final.q,
                        float(np.max(np.abs(final.q - parsed.q[-1]))),
                        False,
                        getattr(driver, "commands_sent", 0) - sent0,
                        tuple(messages),
                    )
        if name in opts.open_at:
            t0 = time.monotonic()
            if gripper is not None:
                gripper.open(opening, watch)
            else:
                driver.gripper_open()
            steps.append(StepRecord(name, "gripper_open", time.monotonic() - t0))
    final = driver.state()
    err = float(np.max(np.abs(final.q - parsed.q[-1])))
    if err > opts.final_tol_rad:
        raise DriverFault(f"plan ended {err:.2e} rad from its last waypoint (tolerance {opts.final_tol_rad:.0e} rad)")
    return ExecutionReport(
        "executed",
        tuple(steps),
        final.q,
        err,
        grip,
        getattr(driver, "commands_sent", 0) - sent0,
        tuple(messages),
    )
