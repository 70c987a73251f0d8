"""The cell loop: capture -> measure -> fit -> plan -> execute -> check the pick, repeated.

Frame sources: `SyntheticBinSource` (a physics-settled bin in the cell, rendered with a sensor model; picks are
checked in MuJoCo against the TRUE poses and picked parts leave the bin) and `BopFrameSource` (frames of a BOP
folder, one pick per frame, nothing to check). A live camera plugs in through the same `FrameSource` protocol.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path
from threading import Event
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell.config import BoxSpec, CellConfig
from normpos_grasp.errors import DriverFault, InputError, RobotModelError, SafetyViolation, ZoneIntrusion
from normpos_grasp.execution.driver import ArmDriver
from normpos_grasp.execution.gripper_config import ToolDriver
from normpos_grasp.execution.plan import ExecuteOptions, ExecutionReport, execute_plan
from normpos_grasp.execution.safety import SafetyLimits
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.pipeline import FrameResult, PipelineOptions, process_frame
from normpos_grasp.planning.capture import plan_capture_move
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.records.template import Template
from normpos_grasp.typing import FloatArray
from normpos_grasp.watch.session import CellWatch

if TYPE_CHECKING:
    from normpos_grasp.replay.bundle import BundleRecorder

log = logging.getLogger(__name__)


class FrameSource(Protocol):
    """Where frames come from and how a pick is checked."""

    def capture(self) -> RGBDFrame:
        """The next frame (camera with world_from_camera). With a wrist camera (`cell.wrist_camera`) the loop sets
        the frame's world_from_camera from the flange pose at capture time; a source that renders its frames has an
        `aim(world_from_camera)` method the loop calls first."""
        ...

    def check_pick(self, plan: PickPlan) -> str:
        """Outcome of the pick just executed: 'held', 'slip', 'drop', 'collision', 'missed' or 'not_checked'."""
        ...

    @property
    def exhausted(self) -> bool:
        """True when there is nothing left to pick or no frame left."""
        ...


@dataclass(frozen=True, eq=False)
class PickRecord:
    """One turn of the loop. status: 'picked', 'pick_failed', 'no_feasible_grasp', 'dry_run', 'driver_fault',
    'unsafe_plan' (the safety limits refused the plan; nothing was sent) or 'zone_stop' (the zone watch stopped the
    arm; the fault names what it saw).

    check: the source's verdict on the pick; timings_ms: per stage, milliseconds (perception, plan, execute, check);
    fault: the fault's type and message for 'driver_fault' (the arm was stopped and nothing further is sent until
    the driver is resumed) and 'unsafe_plan'. captured: the frame as the source gave it (before any depth-bias
    correction; `result.frame` is the corrected one); start_q: (6,) rad the turn planned from (replay bundles).
    """

    index: int
    result: FrameResult
    status: str
    check: str
    plan_json: dict[str, Any] | None
    execution: ExecutionReport | None
    timings_ms: dict[str, float] = field(default_factory=dict)
    fault: str = ""
    captured: RGBDFrame | None = None
    start_q: FloatArray | None = None


class SyntheticBinSource:
    """A bin of `count` parts in `cell`, rendered through the cell's camera with a sensor model.

    parts: names of the library parts to draw from (empty: all); sensor: depth-noise preset. A wrist camera renders
    from the pose `aim` gives (first: capture pose 0).

    Picks are replayed in MuJoCo (`validate_physics`) against the true poses; a held part leaves the bin.
    """

    def __init__(
        self,
        cell: CellConfig,
        count: int = 6,
        seed: int = 0,
        sensor: str = "d435",
        library: list[Template] | None = None,
        validate_physics: bool = True,
        parts: Sequence[str] = (),
    ) -> None:
        from normpos_grasp.sim.cameras import camera_intrinsics
        from normpos_grasp.sim.cell_scene import cell_camera, compose_cell_scene
        from normpos_grasp.sim.sensor import sensor_preset

        self.cell = cell
        self.layout = compose_cell_scene(cell, count, seed, library, parts)
        wrist = cell.wrist_camera
        self.camera = (
            cell_camera(cell, sensor)
            if wrist is None
            else camera_intrinsics(sensor).with_extrinsics(
                wrist.world_from_camera(cell.world_from_base, cell.robot_model, wrist.capture_q[0])
            )
        )
        self.sensor = sensor_preset(sensor)
        self.rng = np.random.default_rng(seed)
        self.validate_physics = validate_physics
        self.last: Any = None  # the last SyntheticFrame (truth for the frame)
        self._frame_index = 0

    @property
    def exhausted(self) -> bool:
        return self.layout.n_parts == 0

    def aim(self, world_from_camera: FloatArray) -> None:
        """Render the next frames from `world_from_camera` (4, 4) (a wrist camera at its capture pose)."""
        self.camera = self.camera.with_extrinsics(world_from_camera)

    def capture(self) -> RGBDFrame:
        from normpos_grasp.sim.dataset import render_frame
        from normpos_grasp.sim.render import make_renderer, release_gl_context

        renderer = make_renderer(self.layout, self.camera.width, self.camera.height)
        try:
            self.last = render_frame(self.layout, renderer, self.camera, self.sensor, self.rng, im_id=self._frame_index)
        finally:
            renderer.close()
            release_gl_context()  # the next capture may come from another thread (run_cell_loop(overlap=True))
        self._frame_index += 1
        return self.last.frame

    def ground_truth_segmenter(self) -> Segmenter:
        """A segmenter returning the true visible masks (labels = part labels) of the frame captured last; checks
        everything after segmentation on its own."""
        return _SyntheticTruth(self)

    def true_part_of(self, plan: PickPlan) -> int:
        """Index of the true part nearest to the plan's target (centre distance), -1 if none is within 5 cm."""
        if plan.chosen is None or self.layout.n_parts == 0:
            return -1
        target = plan.targets[plan.chosen.candidate.target]
        centre = _mesh_centre(target.mesh, target.world_from_object)
        dists = [
            np.linalg.norm(_mesh_centre(t.mesh, self.layout.world_from_object[i]) - centre)
            for i, t in enumerate(self.layout.templates)
        ]
        best = int(np.argmin(dists))
        return best if dists[best] < 0.05 else -1

    def check_pick(self, plan: PickPlan) -> str:
        from normpos_grasp.sim.cell_scene import remove_parts

        part = self.true_part_of(plan)
        if part < 0 or plan.chosen is None:
            return "missed"
        outcome = "not_checked"
        if self.validate_physics:
            from normpos_grasp.sim.physics import PhysicsOptions, validate_grasp

            neighbours = [
                (t, self.layout.world_from_object[i]) for i, t in enumerate(self.layout.templates) if i != part
            ]
            result = validate_grasp(
                self.layout.templates[part],
                self.layout.world_from_object[part],
                neighbours,
                self.layout.static_boxes,
                _physics_gripper(self.cell, plan.tool),
                plan.chosen.candidate.world_from_tcp,
                max(plan.chosen.candidate.opening_m, 1e-3),
                # lift out of the bin (as the plan does) before the sideways shake, so the hand clears the rim
                PhysicsOptions(lift_to_z_m=float(self._entry_z(plan)) + PhysicsOptions().approach_m),
            )
            outcome = result.outcome
            if outcome != "held":
                log.info("physics: pick of part %d %s (%s)", part, outcome, result.reason)
                # a failed pick disturbs the bin: the parts stay where physics left them
                poses = self.layout.world_from_object.copy()
                others = [i for i in range(self.layout.n_parts) if i != part]
                poses[part] = result.world_from_object_final
                poses[others] = result.world_from_neighbours_final
                self.layout = replace(self.layout, world_from_object=poses)
        if outcome in ("held", "not_checked"):
            self.layout = remove_parts(self.layout, [part])
        return outcome

    def _entry_z(self, plan: PickPlan) -> float:
        """The bin entry height of the bin `plan` picks from (the cell's first bin for a one-bin plan), m."""
        return float(self.cell.picking_from(plan.bin).entry_z if plan.bin else self.cell.entry_z)


class _SyntheticTruth:
    """The synthetic bin's ground-truth instances of the frame it rendered last."""

    def __init__(self, source: SyntheticBinSource) -> None:
        self.source = source

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        last = self.source.last
        if last is None or last.frame is not frame:
            raise InputError("the synthetic ground truth only knows the frame its source rendered last")
        return list(last.instances)


class BopFrameSource:
    """Frames of a BOP split or scene folder, in order; picks are not checked (no truth of the outcome).

    world_from_camera: the cell's calibrated extrinsics (4, 4); they replace the dataset's, as for a camera fixed in
    the cell. None keeps the dataset's own `cam_R_w2c`/`cam_t_w2c` (a cell YAML with `camera: {from_scene: true}`).
    """

    def __init__(self, path: str | Path, world_from_camera: FloatArray | None = None) -> None:
        from normpos_grasp.io.bop import BopScene, read_split

        root = Path(path)
        self.root = root
        self.scenes = [BopScene(root)] if (root / "scene_camera.json").is_file() else read_split(root)
        self._frames = [(k, im_id) for k, scene in enumerate(self.scenes) for im_id in scene.frame_ids]
        if not self._frames:
            raise InputError(f"no BOP frames under {root}")
        self._next = 0
        self._world_from_camera = world_from_camera

    @property
    def exhausted(self) -> bool:
        return self._next >= len(self._frames)

    @property
    def n_frames(self) -> int:
        return len(self._frames)

    def capture(self) -> RGBDFrame:
        if self.exhausted:
            raise InputError("the BOP source has no frames left")
        k, im_id = self._frames[self._next]
        self._next += 1
        frame = self.scenes[k].load_frame(im_id)
        camera = frame.camera
        if self._world_from_camera is not None:
            camera = camera.with_extrinsics(self._world_from_camera)
        # scene_id carries the scene's position in this source, so the ground-truth segmenter finds its scene
        return RGBDFrame(frame.rgb, frame.depth_m, camera, frame.stamp, k, frame.im_id)

    def check_pick(self, plan: PickPlan) -> str:
        return "not_checked"

    def part_names(self) -> dict[str, str]:
        """BOP label ('obj_000003') -> part name, from the `parts.json` that `normpos_grasp.sim` writes; {} if none."""
        for folder in (self.root, self.root.parent, self.root.parent.parent):
            info = folder / "parts.json"
            if info.is_file():
                import json

                from normpos_grasp.perception.gt import label_for

                try:
                    parts = json.loads(info.read_text()).get("parts", {})
                    return {label_for(int(obj_id)): str(p["name"]) for obj_id, p in parts.items()}
                except (ValueError, KeyError, TypeError, AttributeError) as exc:
                    raise InputError(f"{info} is not a normpos_grasp parts.json: {exc}") from exc
        return {}

    def ground_truth_segmenter(self, relabel: dict[str, str] | None = None) -> Segmenter:
        """A segmenter returning each frame's ground-truth visible masks (labels mapped through `relabel`)."""
        return _BopGroundTruth(self.scenes, relabel or {})


class _BopGroundTruth:
    """GroundTruthSegmenter per scene of a BopFrameSource (frames carry the scene's index as scene_id)."""

    def __init__(self, scenes: list[Any], relabel: dict[str, str]) -> None:
        from normpos_grasp.perception.gt import GroundTruthSegmenter

        self._segmenters = [GroundTruthSegmenter(scene) for scene in scenes]
        self._relabel = relabel

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        if not 0 <= frame.scene_id < len(self._segmenters):
            raise InputError(f"frame of scene {frame.scene_id} does not come from this BOP source")
        found = self._segmenters[frame.scene_id].segment(frame)
        return [replace(inst, label=self._relabel.get(inst.label, inst.label)) for inst in found]


def run_cell_loop(
    cell: CellConfig,
    source: FrameSource,
    segmenter: Segmenter,
    library: Iterable[Template],
    driver: ArmDriver | None,
    *,
    execute: bool = False,
    max_picks: int = 20,
    options: PipelineOptions | None = None,
    on_pick: Callable[[PickRecord], None] | None = None,
    on_plan: Callable[[FrameResult], None] | None = None,
    bundles: BundleRecorder | None = None,
    gripper: ToolDriver | None = None,
    before_execute: Callable[[PickPlan], None] | None = None,
    watch: CellWatch | None = None,
    overlap: bool = False,
) -> list[PickRecord]:
    """Run picks until the source is exhausted, nothing is feasible, the driver faults, or `max_picks` turns.

    With `execute` False (the default) plans are checked against the safety limits and nothing is sent; the next
    plan then starts where the previous one ended. `on_plan` hears every frame's result before its plan is
    executed (for live views); `on_pick` hears every record. The source checks every pick, also in a dry run (a
    synthetic bin then replays it in physics and loses the part, so a dry run walks through the bin). A
    `DriverFault` during execution ends the loop with a 'driver_fault' record (the driver has stopped the arm and
    sends nothing further until it is resumed); a plan the safety limits refuse ends it with 'unsafe_plan'; a grip
    the gripper's detect input does not confirm ends it with 'pick_failed' (check 'grip_not_detected'). An interrupt
    (KeyboardInterrupt, TerminationRequested) or any other exception leaves through the driver's motion call, which
    stops the arm first. `bundles` (normpos_grasp.replay.BundleRecorder) saves a replay bundle of every record
    (docs/replay.md), after `on_pick`. `gripper` (execution.gripper_config.ToolDriver, connected) is the cell's
    gripper driver: the plan's opening is commanded to it and its grip detection decides 'pick_failed'.
    `before_execute` hears every plan just before it is sent (a simulation puts the part in the emulated gripper).
    `watch` (normpos_grasp.watch.CellWatch, docs/watch.md) checks every frame against the static reference before
    planning (a moved camera raises CameraMoved, saying by how much, and ends the loop) and watches the zones during
    each execution: an intrusion stops the arm and gives a 'zone_stop' record; the loop then follows the resume
    rules (acknowledgement where the cell asks, zones clear, driver resumed) and re-captures, re-measures and
    re-plans from where the arm stopped, never resuming the old plan.

    `overlap`: once the arm has passed the plan's retreat (the part lifted clear of the bin), a worker thread checks
    the pick, captures the next frame and perceives and plans it from the plan's last waypoint while the place
    runs (docs/loop.md, "Overlapped cycles"). The next turn uses that plan only when the pick counted, the cell is
    the one it was planned in and the arm ended where it started; otherwise it re-captures and re-plans. An
    exception in the worker stops the arm (the driver's stop request, or stop() at rest) and leaves the loop with
    that exception; nothing is sent from its plan. Executed plans leave their stream open at the end (the arm held
    at rest; `ExecuteOptions.hold_at_end`) and the prepared next plan goes on in it; the stream is closed before
    anything else is sent and when the loop ends. Not combined with `watch` yet.

    Several bins (`cell.bins`, docs/cells.md "Several bins"): each turn plans from the bin after the one picked
    last (`plan_pick` goes on to the next bins when that one has no part or no feasible pick); a bin the frame
    shows no part in is logged once as empty ("bin 'left' empty") and the loop goes on with the others; it stops
    when every bin is empty (the plan then has nothing to pick).

    A wrist camera (`cell.wrist_camera`, docs/cells.md): each turn first moves the arm to capture pose 0
    (`planning.capture`: a collision-free joint path, checked against the safety limits and run like a plan, or only
    checked in a dry run), takes the frame there with world_from_camera = world_from_base @ base_from_flange(q) @
    flange_from_camera at the joints the driver reports (the commanded ones in a dry run) and plans from there; a
    frame without a feasible grasp moves on to the next capture pose before the turn gives up. A capture move that
    cannot be planned raises PlanningError, one the limits refuse SafetyViolation, a fault on the way DriverFault
    (the driver has stopped the arm). Not combined with `overlap` (the camera cannot see the bin while placing).
    """
    templates = list(library)
    limits = SafetyLimits.from_cell(cell)
    if execute and driver is None:
        raise InputError("execute=True needs a connected driver")
    if overlap and watch is not None:
        raise InputError("overlap is not combined with a zone watch yet: run one or the other")
    if overlap and cell.wrist_camera is not None:
        raise InputError("overlap needs a fixed camera: a wrist camera cannot see the bin while the arm places")
    start_q = driver.state().q if (driver is not None and execute) else np.asarray(cell.home_q, dtype=np.float64)
    # overlapped: a plan's stream stays open at its end for the prepared next plan (execute_plan's hold_at_end)
    run_options = ExecuteOptions(hold_at_end=overlap and execute)
    records: list[PickRecord] = []
    cell_now = cell  # the cell as filled so far: used pattern slots gone, the parts left there static boxes
    ahead: _Lookahead | None = None  # the next turn, perceived and planned while the arm placed (overlap)
    reported_empty: set[str] = set()  # bins logged as empty (a bin seen holding a part again leaves the set)

    def emit(record: PickRecord) -> None:
        record = replace(record, captured=frame, start_q=cycle_q)  # this turn's frame and start joints
        records.append(record)
        if on_pick is not None:
            on_pick(record)
        if bundles is not None:  # the cell as this turn planned in (pattern slots used so far, parts left there)
            _end_stream(driver)  # saving takes a while: no stream held open meanwhile
            bundles.save(record, cycle_cell, templates, options or PipelineOptions())

    # overlap: every capture and the worker run on one thread (a renderer's GL context stays on its thread)
    pool_cm: AbstractContextManager[ThreadPoolExecutor | None] = (
        ThreadPoolExecutor(1, thread_name_prefix="normpos-overlap") if overlap else nullcontext()
    )
    with pool_cm as pool, _overlap_session(driver if execute else None, overlap):
        for index in range(max_picks):
            if source.exhausted:
                break
            if not cell_now.places:
                log.warning("every place slot of cell %r is filled: loop stopped", cell.name)
                break
            cycle_cell = cell_now
            if ahead is not None and ahead.usable(start_q, cell_now):
                assert ahead.frame is not None and ahead.result is not None
                frame, result, cycle_q = ahead.frame, ahead.result, ahead.start_q  # the plan starts where the arm is
                timings = {"capture": ahead.capture_ms, **result.timings_ms, "overlap_wait": ahead.wait_ms}
            else:
                _end_stream(driver)  # the last plan's stream, held for a prepared plan that is not coming
                views = _capture_order(cell_now)
                for view in views:  # a wrist camera tries its capture poses in turn
                    t0 = time.perf_counter()
                    if cell.wrist_camera is not None:
                        frame = wrist_capture(cell_now, source, driver if execute else None, start_q, limits, view)
                        start_q = capture_joints(cell_now, driver if execute else None, view)
                    else:
                        frame = pool.submit(source.capture).result() if pool is not None else source.capture()
                    cycle_q = np.array(start_q, dtype=np.float64)
                    t_capture = (time.perf_counter() - t0) * 1e3
                    if watch is not None:
                        watch.check_drift(frame)  # CameraMoved ends the loop before a moved camera is planned from
                    result = process_frame(frame, segmenter, templates, cell_now, options, cycle_q)
                    timings = {"capture": t_capture, **result.timings_ms}
                    if result.plan is not None and result.plan.status == "ok":
                        break
                    if view != views[-1]:
                        log.info("pick %d: no feasible grasp from capture pose %d: trying the next", index + 1, view)
            ahead = None
            if on_plan is not None:
                on_plan(result)
            plan = result.plan
            empty_now = set(plan.bins_empty) if plan is not None else set()
            for name in sorted(empty_now - reported_empty):
                log.info("pick %d: bin %r empty", index + 1, name)
            reported_empty = empty_now
            if plan is None or plan.status != "ok":
                doc = plan.to_json() if plan is not None else None
                if plan is not None and len(cell.bins) > 1 and len(plan.bins_empty) == len(cell.bins):
                    log.info("every bin of cell %r is empty: loop stopped", cell.name)
                emit(PickRecord(index, result, "no_feasible_grasp", "not_checked", doc, None, timings))
                break
            plan_json = plan.to_json()
            cell_next = with_placed(cell_now, plan)  # the cell once this part is down (the next turn plans in it)
            if plan.bin:  # several bins: the next turn starts at the bin after this one
                cell_next = cell_next.picking_from(cell.next_bin(plan.bin))
            look: _Lookahead | None = None
            if overlap:
                plan_next = index + 1 < max_picks and bool(cell_next.places)
                assert pool is not None
                look = _Lookahead(
                    pool, source, segmenter, templates, options, plan, cell_next, driver if execute else None, plan_next
                )
            t0 = time.perf_counter()
            try:
                if execute and before_execute is not None:
                    before_execute(plan)
                with (
                    (
                        watch.watching(frame, driver, cycle_q, watch.held_radius(plan))
                        if (watch is not None and execute)
                        else nullcontext()
                    ),
                    look.running() if look is not None else nullcontext(),
                ):
                    report = execute_plan(
                        driver,
                        plan_json,
                        plan_limits(cell, plan, limits),
                        dry_run=not execute,
                        gripper=gripper,
                        options=run_options,
                    )
            except ZoneIntrusion as exc:
                timings["execute"] = (time.perf_counter() - t0) * 1e3
                log.error("pick %d: zone stop: %s", index + 1, exc)
                fault = f"ZoneIntrusion: {exc}"
                emit(PickRecord(index, result, "zone_stop", "not_checked", plan_json, None, timings, fault))
                if watch is None or driver is None or not watch.after_stop(driver, exc):
                    break
                start_q = driver.state().q  # re-capture, re-measure and re-plan from here; the old plan is dropped
                continue
            except (DriverFault, SafetyViolation) as exc:
                timings["execute"] = (time.perf_counter() - t0) * 1e3
                status = "driver_fault" if isinstance(exc, DriverFault) else "unsafe_plan"
                log.error("pick %d: %s: %s", index + 1, type(exc).__name__, exc)
                fault = f"{type(exc).__name__}: {exc}"
                emit(PickRecord(index, result, status, "not_checked", plan_json, None, timings, fault))
                break
            timings["execute"] = (time.perf_counter() - t0) * 1e3
            if report.status == "grip_failed":
                if look is not None:
                    look.cancel()  # the arm rests at the grasp: the worker never got past the retreat
                # the grip-detect input stayed low: the pick stopped at the grasp, the arm at rest; the operator acts
                log.error("pick %d: grip not detected after closing; loop stopped", index + 1)
                fault = "grip not detected after closing: pick stopped at the grasp"
                emit(PickRecord(index, result, "pick_failed", "grip_not_detected", plan_json, report, timings, fault))
                break
            if look is not None:
                look.finish(driver if execute else None)  # raises the worker's exception with the arm stopped
                assert look.check is not None
                check = look.check
                timings["check"] = look.check_ms
                ahead = look
            else:
                t0 = time.perf_counter()
                check = source.check_pick(plan)  # synthetic bins replay the pick in physics, dry run or not
                timings["check"] = (time.perf_counter() - t0) * 1e3
            status = "dry_run" if not execute else ("picked" if check in ("held", "not_checked") else "pick_failed")
            if status in ("picked", "dry_run"):
                cell_now = cell_next
            if execute and driver is not None:
                start_q = driver.state().q
            elif plan.waypoints:
                start_q = np.asarray(plan.waypoints[-1].q, dtype=np.float64)
            emit(PickRecord(index, result, status, check, plan_json, report, timings))
    return records


class _Lookahead:
    """The next turn of an overlapped loop, prepared on the loop's capture thread while the arm carries out `plan`.

    The worker waits until the arm has passed the plan's retreat (the trajectory sample nearest the arm's joints,
    searched from the grasp on; without a driver, at once), then checks the pick (`source.check_pick`) and, when it
    counted and `plan_next`, captures the next frame and runs perception and planning in `cell` (the cell with this
    part placed) from the plan's last waypoint. The main thread's `running()` wraps the execution: a worker failure
    during the motion asks the driver to stop the arm; the motion call then raises and the worker's exception
    leaves the loop.
    """

    def __init__(
        self,
        pool: ThreadPoolExecutor,
        source: FrameSource,
        segmenter: Segmenter,
        templates: list[Template],
        options: PipelineOptions | None,
        plan: PickPlan,
        cell: CellConfig,
        driver: ArmDriver | None,
        plan_next: bool,
        poll_s: float = 0.004,
    ) -> None:
        self.source, self.segmenter, self.templates, self.options = source, segmenter, templates, options
        self.plan, self.cell, self.driver, self.plan_next, self.poll_s = plan, cell, driver, plan_next, poll_s
        self.start_q = np.asarray(plan.waypoints[-1].q, dtype=np.float64) if plan.waypoints else np.zeros(6)
        self.check: str | None = None
        self.frame: RGBDFrame | None = None
        self.result: FrameResult | None = None
        self.error: BaseException | None = None
        self.capture_ms = self.check_ms = self.wait_ms = 0.0
        self._go = Event()  # the execution returned: go on even if the retreat was never seen
        self._cancel = Event()
        self._pool = pool
        self._future: Future[None] | None = None

    def _retreat_passed(self) -> bool:
        traj = self.plan.trajectory
        names = [w.name for w in self.plan.waypoints]
        if self.driver is None:
            return True
        if traj is None or "retreat" not in names or "grasp" not in names:
            return False  # no timed path to follow: wait for the end of the execution
        q = self.driver.state().q
        wq = [w.q for w in self.plan.waypoints]
        grasp = int(np.argmin(np.abs(traj.q - wq[names.index("grasp")]).max(axis=1)))
        retreat = grasp + int(np.argmin(np.abs(traj.q[grasp:] - wq[names.index("retreat")]).max(axis=1)))
        here = grasp + int(np.argmin(np.abs(traj.q[grasp:] - q).max(axis=1)))
        return here >= retreat

    def _run(self) -> None:
        try:
            while not self._cancel.is_set() and not self._go.is_set() and not self._retreat_passed():
                time.sleep(self.poll_s)
            if self._cancel.is_set():
                return
            t0 = time.perf_counter()
            self.check = self.source.check_pick(self.plan)
            self.check_ms = (time.perf_counter() - t0) * 1e3
            if self.check not in ("held", "not_checked") or not self.plan_next or self.source.exhausted:
                return  # the bin changed in a way a frame taken now would not be planned on; the next turn re-plans
            t0 = time.perf_counter()
            frame = self.source.capture()
            self.capture_ms = (time.perf_counter() - t0) * 1e3
            if self._cancel.is_set():
                return
            result = process_frame(frame, self.segmenter, self.templates, self.cell, self.options, self.start_q)
            self.frame, self.result = frame, result
        except BaseException as exc:  # handed to the main thread, which stops the arm and re-raises
            self.error = exc
            request = getattr(self.driver, "request_stop", None)
            if callable(request):
                request(f"overlap worker failed: {type(exc).__name__}: {exc}")

    def start(self) -> _Lookahead:
        self._future = self._pool.submit(self._run)
        return self

    def _join(self) -> None:
        if self._future is not None:
            self._future.result()  # _run keeps its exception in self.error

    @contextmanager
    def running(self) -> Iterator[_Lookahead]:
        """Around the execution: starts the worker; a motion call that raised cancels it, and when the worker had
        asked for that stop, its exception is the one that leaves."""
        self.start()
        try:
            yield self
        except BaseException as exc:
            self.cancel()
            if self.error is not None:
                raise self.error from exc
            raise

    def cancel(self) -> None:
        self._cancel.set()
        self._join()

    def finish(self, driver: ArmDriver | None) -> None:
        """Wait for the worker (the execution has returned); its exception is raised after `driver.stop()`."""
        t0 = time.perf_counter()
        self._go.set()
        if driver is not None and self._future is not None and not self._future.done():
            _end_stream(driver)  # the worker is still at it: no stream held open while the loop waits
        self._join()
        self.wait_ms = (time.perf_counter() - t0) * 1e3
        if self.error is not None:
            if driver is not None:
                driver.stop()
            raise self.error

    def usable(self, start_q: FloatArray, cell: CellConfig, tol_rad: float = 1e-3) -> bool:
        """The prepared plan holds: a result exists, the cell is the one it planned in, the arm is at its start."""
        if self.result is None or self.frame is None or cell is not self.cell:
            return False
        err = float(np.max(np.abs(np.asarray(start_q, dtype=np.float64) - self.start_q)))
        if err > tol_rad:
            log.warning("overlap: the arm is %.2e rad from the prepared plan's start: re-planned", err)
            return False
        return True


def wrist_capture(
    cell: CellConfig,
    source: FrameSource,
    driver: ArmDriver | None,
    start_q: FloatArray,
    limits: SafetyLimits,
    view: int,
) -> RGBDFrame:
    """Move the arm from `start_q` (6,) rad to capture pose `view` of the cell's wrist camera (with `driver`
    None: only checked against `limits`), then take a frame there whose camera carries world_from_camera =
    world_from_base @ base_from_flange(q) @ flange_from_camera at the joints q the driver reports after the move (the
    capture joints without a driver). A source with `aim` is told that pose first (a renderer draws from it)."""
    wrist = cell.wrist_camera
    if wrist is None:
        raise InputError(f"cell {cell.name!r} has no wrist camera")
    move = plan_capture_move(cell, start_q, view)
    execute_plan(driver, move.to_json(cell), limits, dry_run=driver is None, options=_CAPTURE_MOVE)
    q = capture_joints(cell, driver, view)
    world_from_camera = wrist.world_from_camera(cell.world_from_base, cell.robot_model, q)
    aim = getattr(source, "aim", None)
    if callable(aim):
        aim(world_from_camera)
    frame = source.capture()
    seen = frame.camera.world_from_camera
    if seen is not None and np.allclose(seen, world_from_camera, atol=1e-9):
        return frame  # the source drew it from there (its ground truth knows this frame object)
    return RGBDFrame(
        frame.rgb,
        frame.depth_m,
        frame.camera.with_extrinsics(world_from_camera),
        frame.stamp,
        frame.scene_id,
        frame.im_id,
    )


def _capture_order(cell: CellConfig) -> list[int]:
    """The capture poses a turn tries, in order: [0] for a fixed camera; a wrist camera's poses with the one that
    sees the bin picked from first (its `capture:`) in front."""
    if cell.wrist_camera is None:
        return [0]
    order = list(range(len(cell.wrist_camera.capture_q)))
    first = cell.bin.capture if cell.bin is not None else None
    return order if first is None else [first, *(v for v in order if v != first)]


#: GIL switch interval while an overlapped loop executes, s: the stream's ticks (every 8 ms) wait at most this long
#: for the worker's perception and planning to hand the interpreter back (Python's default: 5 ms)
OVERLAP_SWITCH_INTERVAL_S = 0.0005


@contextmanager
def _overlap_session(driver: ArmDriver | None, overlap: bool) -> Iterator[None]:
    """Around an overlapped loop: the interpreter's switch interval lowered to `OVERLAP_SWITCH_INTERVAL_S` (restored
    after), and with a driver, a stream left open at a plan's end (`ExecuteOptions.hold_at_end`) closed on every way
    out."""
    if not overlap:
        yield
        return
    old = sys.getswitchinterval()
    sys.setswitchinterval(min(old, OVERLAP_SWITCH_INTERVAL_S))
    try:
        yield
    finally:
        sys.setswitchinterval(old)
        if driver is not None:
            _end_stream(driver)


def _end_stream(driver: ArmDriver | None) -> None:
    """Close a stream the driver holds open (GuardedDriver.end_stream); nothing for other drivers."""
    end = getattr(driver, "end_stream", None)
    if callable(end):
        end()


# the move to a capture pose: no gripper action, the arm ends at the capture joints
_CAPTURE_MOVE = ExecuteOptions(close_at=(), open_at=(), open_first=False, check_grip=False)


def capture_joints(cell: CellConfig, driver: ArmDriver | None, view: int) -> FloatArray:
    """(6,) rad the arm stands at for a wrist capture: the driver's joints, else capture pose `view`."""
    if driver is not None:
        return np.asarray(driver.state().q, dtype=np.float64)
    if cell.wrist_camera is None:
        raise InputError(f"cell {cell.name!r} has no wrist camera")
    return np.asarray(cell.wrist_camera.capture_q[view], dtype=np.float64)


def with_placed(cell: CellConfig, plan: PickPlan) -> CellConfig:
    """`cell` after `plan` put its part down: a single-use place (a pattern slot) leaves the list of places and the
    part left there, as its box (the fitted template's bounds at the release pose), joins the static boxes that every
    later plan collides with. A reusable place pose changes nothing."""
    place = next((p for p in cell.places if p.name == plan.place), None)
    if place is None or not place.single_use or plan.chosen is None:
        return cell
    c = plan.chosen.candidate
    target = plan.targets[c.target]
    release = next(w for w in plan.waypoints if w.name == "place")
    world_from_object = (
        np.asarray(release.world_from_tcp) @ np.linalg.inv(c.world_from_tcp) @ np.asarray(target.world_from_object)
    )
    lo, hi = np.asarray(target.mesh.bounds, dtype=np.float64)  # type: ignore[attr-defined]
    centre = np.eye(4)
    centre[:3, 3] = (lo + hi) / 2.0
    box = BoxSpec(f"placed/{place.name}", world_from_object @ centre, hi - lo)
    return replace(
        cell,
        places=tuple(p for p in cell.places if p.name != place.name),
        static_boxes=(*cell.static_boxes, box),
    )


def _mesh_centre(mesh: Any, world_from_object: FloatArray) -> FloatArray:
    centre = np.asarray(mesh.bounds, dtype=np.float64).mean(axis=0)
    pose = np.asarray(world_from_object, dtype=np.float64)
    return pose[:3, :3] @ centre + pose[:3, 3]


def plan_limits(cell: CellConfig, plan: PickPlan, limits: SafetyLimits) -> SafetyLimits:
    """The limits that judge `plan`: `limits` (the cell's), or on a dual-tool flange `limits` with the plan's tool
    mounted (its TCP for the workspace box and the plan's tool check); every cap and the box stay those given, so
    limits tightened by the caller are never loosened here."""
    if len(cell.tools) == 1:
        return limits
    tool = cell.tool_named(plan.tool.name)[0]
    return replace(limits, flange_from_tcp=np.array(tool.flange_from_tcp, dtype=np.float64))


def tool_outputs_hook(cell: CellConfig, driver: Any) -> Callable[[PickPlan], None]:
    """For a dual-tool cell on a driver that switches its outputs in this process (the simulated one, the demo's
    loopback controller): before each plan is sent, the driver's gripper outputs become those of the plan's tool
    (its `gripper[i].driver` wiring: the cup's vacuum and release outputs, the jaws' close / open) and its limits
    those with that tool's TCP (`plan_limits`). No grip-detect input is read there (nothing in the simulated arm
    drives one): the source's check judges the pick, as for a one-tool cell on these drivers."""
    from normpos_grasp.execution.driver import GripperIO
    from normpos_grasp.execution.gripper_config import gripper_io

    def hook(plan: PickPlan) -> None:
        wiring = gripper_io(cell.tool_named(plan.tool.name)[1]) or GripperIO()
        driver.gripper = replace(wiring, grip_detect_input=None)
        driver.limits = plan_limits(cell, plan, driver.limits)

    return hook


def _physics_gripper(cell: CellConfig, tool: Any = None) -> Any:
    """The physics model of the cell's gripper: the packaged gripper of that name, else one built from the tool; on
    a dual-tool flange that of `tool` (the plan's; default the first) with the idle tool's body."""
    from normpos_grasp.kinematics.gripper import Gripper
    from normpos_grasp.sim.physics import GripperSpec

    if len(cell.tools) > 1:
        from normpos_grasp.sim.tool_hand import tool_spec

        return tool_spec(tool if tool is not None else cell.tool)

    try:
        return Gripper.load(cell.tool.name)
    except RobotModelError:
        return GripperSpec(kind=cell.tool.kind, name=cell.tool.name, stroke_m=max(cell.tool.stroke_m, 1e-3))
