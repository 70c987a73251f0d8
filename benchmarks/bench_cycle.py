"""Pick-and-place cycle time: the arm-motion duration of a plan (home -> bin -> grasp -> place), before/after.

Bins: `loop.SyntheticBinSource` in examples/cells/ur5e_bin_parallel.yaml (`--parts` physics-settled parts, seeds
`--seed`, `--seed` + 1, ...), perceived with the frame's true masks (`perceive`, everything after segmentation as
the pipeline runs it) and planned with `plan_pick` once per variant, same fits, same deterministic planner:
- nearest branches, trapezoid: `PlanOptions(quickest_branches=False)`, `TimingOptions(method='trapezoid')`: the
  evaluation's joint angles, the place pose as given, rest-to-rest trapezoids per segment (the first timing);
- nearest branches, ruckig: the same branches timed by `planning.timing.time_path` (time-optimal, jerk-limited,
  blending through waypoints): the cycle before `planning.branches`;
- quickest branches, ruckig: the default: joint 6 turned the quicker way at the grasp (a half turn where the tool
  looks the same), the equivalent place pose and IK branch with the quickest estimated transfer;
- jerk 50: the default with the former jerk cap, 50 rad/s^3 (what the planner's 100 rad/s^3 saves);
- no blends: the default resting at every waypoint (what blending adds);
- jerk xF: `--jerk-factor` times the default jerk cap (what a sharper jerk cap would save; not a cell cap: the
  servo stream bounds it, see below, and the planner re-times the plans whose stream exceeds at a halved cap).
Each plan's arm motion is split at its waypoints: approach (home -> entry), descend (entry -> grasp), lift
(grasp -> retreat), transfer (retreat -> pre_place), place (pre_place -> place), retreat (place -> post_place).
Every plan is then checked as execution checks it before sending: plan.json round trip, `execution.plan.check_plan`
with `SafetyLimits.from_cell` (waypoints, segments, every trajectory sample: joint limits, workspace, speed and
acceleration caps by finite differences); the largest sample speed, acceleration and jerk are printed as shares of
the caps, and the largest distance of the TCP from its straight line between the Cartesian waypoints. The servo
commands execution would stream (`execution.driver.stream_samples` every 8 ms through the pieces between the
gripper's waypoints, home -> grasp -> place -> post_place) are checked against the same caps as the driver checks
them before the first is sent: their largest speed or acceleration share, and the plans the driver would refuse.
The planner runs that check itself and re-times a plan whose stream exceeds with its jerk cap halved
(`planning.plan._timed_for_stream`): 're-timed' counts the plans it re-timed (its debug log, captured here).

    nice -n 10 .venv/bin/python benchmarks/bench_cycle.py [--bins 6] [--parts 10] [--seed 5200]
"""

from __future__ import annotations

import argparse
import logging
import os
from dataclasses import replace
from typing import Any

import numpy as np

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.stream import stream_cuts, stream_samples
from normpos_grasp.errors import SafetyViolation
from normpos_grasp.execution.driver import DriverOptions
from normpos_grasp.execution.plan import check_plan, parse_plan
from normpos_grasp.execution.safety import SafetyLimits
from normpos_grasp.kinematics.ur_params import dh_forward_kinematics, ur_params
from normpos_grasp.loop import SyntheticBinSource
from normpos_grasp.pipeline import PipelineOptions, perceive
from normpos_grasp.planning.plan import STREAM_CUTS, PlanOptions, plan_pick
from normpos_grasp.planning.timing import TimingOptions
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.sim.parts import default_part_library

CELL = "examples/cells/ur5e_bin_parallel.yaml"
LINES: tuple[tuple[str, str], ...] = (
    ("entry", "pre_grasp"),
    ("pre_grasp", "grasp"),
    ("grasp", "lift"),
    ("lift", "retreat"),
)
LINES += (("pre_place", "place"), ("place", "post_place"))


def line_deviation_mm(plan: PickPlan, cell: Any) -> float:
    """Largest distance (mm) of a trajectory sample's TCP from the straight line of its Cartesian segment."""
    traj = plan.trajectory
    assert traj is not None
    names = [w.name for w in plan.waypoints]
    wq = [w.q for w in plan.waypoints]
    idx = [int(np.argmin(np.abs(traj.q - q).max(axis=1))) for q in wq]
    for k in range(1, len(idx)):  # in order (post_place repeats pre_place)
        if idx[k] < idx[k - 1]:
            later = np.abs(traj.q[idx[k - 1] :] - wq[k]).max(axis=1)
            idx[k] = idx[k - 1] + int(np.argmin(later))
    world_tcp = cell.world_from_base @ dh_forward_kinematics(ur_params(cell.robot_model), traj.q)
    tcp = (world_tcp @ cell.tool.flange_from_tcp)[:, :3, 3]
    worst = 0.0
    for a, b in LINES:
        i, j = idx[names.index(a)], idx[names.index(b)]
        p0, p1 = (
            plan.waypoints[names.index(a)].world_from_tcp[:3, 3],
            plan.waypoints[names.index(b)].world_from_tcp[:3, 3],
        )
        u = (p1 - p0) / max(float(np.linalg.norm(p1 - p0)), 1e-12)
        rel = tcp[i : j + 1] - p0
        worst = max(worst, float(np.linalg.norm(rel - np.outer(rel @ u, u), axis=1).max()))
    return worst * 1e3


SEGMENTS = (
    ("approach", "home", "entry"),
    ("descend", "entry", "grasp"),
    ("lift", "grasp", "retreat"),
    ("transfer", "retreat", "pre_place"),
    ("place", "pre_place", "place"),
    ("retreat", "place", "post_place"),
)


def segment_times(plan: PickPlan) -> list[float]:
    """Seconds of arm motion per SEGMENTS entry: between the trajectory samples at the plan's waypoints (each
    waypoint is a sample of the trajectory; found in order, post_place repeating pre_place's pose)."""
    traj = plan.trajectory
    assert traj is not None
    at: dict[str, float] = {}
    start = 0
    for w in plan.waypoints:
        i = start + int(np.argmin(np.abs(traj.q[start:] - w.q).max(axis=1)))
        at[w.name], start = float(traj.t[i]), i
    return [at[b] - at[a] for _, a, b in SEGMENTS]


def streamed_share(plan: PickPlan, limits: SafetyLimits) -> tuple[float, bool]:
    """Largest speed or acceleration share of the caps of the servo commands execution streams for `plan` (pieces
    split at the grasp and the place, as `execution.plan.execute_plan` streams them) and whether the driver's
    check (`check_trajectory(..., "streamed commands")`) passes them all."""
    parsed = parse_plan(plan.to_json())
    t, q = parsed.traj_t, parsed.traj_q
    assert t is not None and q is not None
    cuts = stream_cuts(q, parsed.names, parsed.q, STREAM_CUTS)
    worst, ok = 0.0, True
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        sent_t, sent = stream_samples(t[a : b + 1], q[a : b + 1], DriverOptions().stream_period_s)
        try:
            limits.check_trajectory(sent_t, sent, "streamed commands")
        except SafetyViolation:
            ok = False
        dt = np.diff(sent_t)
        qd = np.diff(sent, axis=0) / dt[:, None]
        qdd = np.diff(qd, axis=0) / (0.5 * (dt[1:] + dt[:-1]))[:, None]
        share = max(
            float(np.max(np.abs(qd) / limits.max_joint_speed)), float(np.max(np.abs(qdd) / limits.max_joint_accel))
        )
        worst = max(worst, share)
    return worst, ok


def cap_shares(plan: PickPlan, limits: SafetyLimits, jerk_cap: float) -> tuple[float, float, float]:
    """Largest |speed|, |acceleration| and |jerk| of the samples (finite differences) as shares of the caps."""
    traj = plan.trajectory
    assert traj is not None
    t, q = traj.t, traj.q
    dt = np.diff(t)
    qd = np.diff(q, axis=0) / dt[:, None]
    tm = 0.5 * (t[1:] + t[:-1])
    qdd = np.diff(qd, axis=0) / np.diff(tm)[:, None]
    qddd = np.diff(qdd, axis=0) / np.diff(0.5 * (tm[1:] + tm[:-1]))[:, None]
    return (
        float(np.max(np.abs(qd) / limits.max_joint_speed)),
        float(np.max(np.abs(qdd) / limits.max_joint_accel)),
        float(np.max(np.abs(qddd)) / jerk_cap),
    )


class _Retimes(logging.Handler):
    """Counts the planner's 'servo stream refused ... re-timed' records (planning.plan._timed_for_stream)."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage().startswith("servo stream refused"):
            self.count += 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bins", type=int, default=6)
    parser.add_argument("--parts", type=int, default=10)
    parser.add_argument("--seed", type=int, default=5200)
    parser.add_argument("--jerk-factor", type=float, default=1.5)
    args = parser.parse_args()
    cell = load_cell(CELL)
    library = default_part_library()
    limits = SafetyLimits.from_cell(cell)
    retimes = _Retimes()
    plan_log = logging.getLogger("normpos_grasp.planning.plan")
    plan_log.addHandler(retimes)
    plan_log.setLevel(logging.DEBUG)
    plan_log.propagate = False  # the counter only: the planner's other records are not printed
    base = TimingOptions()
    nearest = PlanOptions(quickest_branches=False)
    variants = {
        "nearest branches, trapezoid": replace(nearest, timing=TimingOptions(method="trapezoid")),
        "nearest branches, ruckig (before)": nearest,
        "quickest branches, ruckig, jerk 50 (before)": PlanOptions(timing=replace(base, jerk_rad_s3=50.0)),
        "quickest branches, ruckig (after)": PlanOptions(),
        "quickest branches, ruckig, no blends": PlanOptions(timing=replace(base, blend=False)),
        f"quickest branches, ruckig, jerk x{args.jerk_factor:g}": PlanOptions(
            timing=replace(base, jerk_rad_s3=base.jerk_rad_s3 * args.jerk_factor)
        ),
    }
    print("# bench_cycle")
    print(
        f"cell {CELL}: caps {cell.motion.joint_velocity[0]:g} rad/s, {cell.motion.joint_acceleration[0]:g} rad/s^2, "
        f"jerk {base.jerk_rad_s3:g} rad/s^3 (planner default), TCP {cell.motion.tcp_speed_m_s:g} m/s and "
        f"{cell.motion.tcp_acceleration_m_s2:g} m/s^2 on lines; {args.bins} bins of {args.parts} parts"
    )
    print(f"load average before: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")
    # the loop plans each next cycle from where the last one ended: the same bin planned again from the post-place
    steady = {k: f"{k.split(' (')[0]}, from the post-place" for k in variants if "(" in k and "trapezoid" not in k}
    names = [*variants, *steady.values()]
    rows: dict[str, list[tuple[float, ...]]] = {k: [] for k in names}
    parts: dict[str, list[list[float]]] = {k: [] for k in names}
    for b in range(args.bins):
        source = SyntheticBinSource(cell, count=args.parts, seed=args.seed + b, validate_physics=False, library=library)
        frame = source.capture()
        result = perceive(frame, source.ground_truth_segmenter(), library, PipelineOptions())
        line = []
        todo: list[tuple[str, PlanOptions, Any]] = [(k, o, None) for k, o in variants.items()]
        while todo:
            name, options, start_q = todo.pop(0)
            retimes.count = 0
            plan = plan_pick(result.fits, result.normpositions, cell, options, start_q=start_q)
            if plan.status != "ok" or plan.trajectory is None:
                line.append(f"{name}: {plan.status}")
                continue
            check_plan(parse_plan(plan.to_json()), limits)  # raises SafetyViolation: nothing would be sent
            v, a, j = cap_shares(plan, limits, base.jerk_rad_s3)
            dev = line_deviation_mm(plan, cell)
            sv, sent_ok = streamed_share(plan, limits)
            rows[name].append(
                (
                    plan.trajectory.duration_s,
                    v,
                    a,
                    j,
                    dev,
                    plan.timing_ms.get("timing", 0.0),
                    sv,
                    float(not sent_ok),
                    float(retimes.count > 0),
                )
            )
            parts[name].append(segment_times(plan))
            line.append(f"{name}: {plan.trajectory.duration_s:.2f} s")
            if name in steady:
                todo.append((steady[name], options, plan.waypoints[-1].q))
        print(f"bin {b} (seed {args.seed + b}): " + ", ".join(line))
    print("\n## Cycle (plan trajectory duration) and checks, per variant")
    print(
        "| timing | plans | median s | max s | max speed / cap | max accel / cap | max jerk / default cap | "
        "max line deviation mm | timing ms (median) | max streamed / cap | stream refused | re-timed |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, rs in rows.items():
        if not rs:
            print(f"| {name} | 0 | - | - | - | - | - | - | - | - | - | - |")
            continue
        r = np.array(rs)
        print(
            f"| {name} | {len(rs)} | {np.median(r[:, 0]):.2f} | {r[:, 0].max():.2f} | {r[:, 1].max():.3f} | "
            f"{r[:, 2].max():.3f} | {r[:, 3].max():.2f} | {r[:, 4].max():.3f} | {np.median(r[:, 5]):.1f} | "
            f"{r[:, 6].max():.4f} | {int(r[:, 7].sum())} | {int(r[:, 8].sum())} |"
        )
    print("every plan passed execution.plan.check_plan (SafetyLimits.from_cell) on its plan.json")
    print(
        "max streamed / cap: the servo commands (8 ms) the driver checks before sending; refused: plans it would stop;"
        " re-timed: plans the planner re-timed with a halved jerk cap because their stream exceeded"
    )
    print(
        "\n## Where the seconds go: median s per segment (over the bins; 'approach' starts at home or the post-place)"
    )
    print("| variant | " + " | ".join(name for name, _, _ in SEGMENTS) + " | cycle |")
    print("|---|" + "---|" * (len(SEGMENTS) + 1))
    for name, ps in parts.items():
        if ps:
            med = np.median(np.array(ps), axis=0)
            cycle = np.median(np.array(rows[name])[:, 0])
            print(f"| {name} | " + " | ".join(f"{m:.2f}" for m in med) + f" | {cycle:.2f} |")
    print(f"load average after: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
