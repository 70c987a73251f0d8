"""One simulated bin-clearing episode: scene -> (render, segment, measure, fit, plan, physics) per pick.

`run_scene(config, scene_index)` composes a settled scene of the default parts in the cell's bin, renders it
through the cell's camera with the chosen sensor's noise, runs the real pipeline on the noisy frame (instances
that change detection finds unchanged since the previous frame keep their fits), validates the chosen grasp in
MuJoCo against the TRUE part poses, updates the scene from the physics' end state (a held part leaves,
everything else lies where physics left it) and repeats until the bin is empty, the planner finds no feasible
grasp, or `max_consecutive_failures` picks in a row failed. Before it gives up on a frame without a feasible
grasp, the cell plans once more with relaxed margins, nudges a part (a push planned on the perceived scene,
replayed in physics) and captures a fresh frame. Everything is seeded from (config.seed, scene_index): the
same call gives the same records on any machine and worker layout.

A wrist-camera cell (`camera: {mount: wrist}`) moves to its capture pose before every frame: the move from where
the last plan ended (home at the start) is planned (`planning.capture`, camera housing included), the frame is
rendered from world_from_base @ base_from_flange(q_capture) @ flange_from_camera, and the pick is planned from the
capture joints; a fresh capture (a perception retry) uses the next capture pose. A capture move that cannot be
planned ends the scene with 'no_feasible_grasp'.

Failure causes of a pick (first that applies): 'segmentation_miss' (no instance found, or the chosen instance
covers no true part with IoU >= `match_iou`), 'wrong_fit' (no template fit was accepted, or the physics failed
and the fitted pose is off the true one by more than `wrong_fit_m`), 'no_feasible_grasp' (accepted fits but
the planner found no grasp), 'collision' (the hand hit
something), 'physics_drop' (missed, dropped or slipped).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError, NormposError
from normpos_grasp.geometry.transforms import make_pose, transform_points
from normpos_grasp.measure.measure import MeasureOptions
from normpos_grasp.perception.change import mask_iou
from normpos_grasp.pipeline import FrameResult, PipelineOptions, ReuseOptions, perceive
from normpos_grasp.planning.evaluate import EvaluationOptions
from normpos_grasp.planning.plan import PLANNING_PASSES, predicted_success, rejections_by_target, stop_line
from normpos_grasp.planning.push import Push, PushHand
from normpos_grasp.records.template import Template
from normpos_grasp.sim.physics import GripperSpec, PhysicsOptions, PhysicsResult, validate_grasp
from normpos_grasp.sim.tool_hand import PRESETS, tool_spec
from normpos_grasp.simulate.trace import LeftPart, dominant_reason, failure_picture, left_parts
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)

CAUSES = ("segmentation_miss", "wrong_fit", "no_feasible_grasp", "physics_drop", "collision")
#: what produced a pick's grasp (`PickRecord.kind`, `grasp_kind`): the planner's passes (`PLANNING_PASSES`:
#: 'first', 'turned', 'leaned'), simulate's relaxed-margin pass, or a manipulation made before it ('drag', 'push')
KINDS = (*PLANNING_PASSES, "relaxed", "drag", "push")
SEGMENTERS = ("model", "gt", "depth")


@dataclass(frozen=True)
class SimulationConfig:
    """What a batch simulates (picklable: workers and Ray tasks receive it as is).

    cell_path: cell YAML. sensor: sensor model name ('d435', 'ideal', ...). seed: batch seed.
    parts: part names drawn into each scene (empty = the whole default library). parts_per_scene: how many.
    segmenter: 'model' (the bundled RGB-D segmentation model: the product's pipeline), 'gt' (the rendering's
    visible masks with labels: an ideal segmenter) or 'depth' (model-free depth segmentation, labels left to the
    template fit). renderer: 'auto', 'mujoco' or 'raycast'.
    match_iou: an instance matches a true part at this mask IoU. wrong_fit_m: a fitted pose whose model points
    lie this far (mean, symmetric closest point) from the true ones counts as a wrong fit, metres.
    max_consecutive_failures: an episode stops after this many failed picks in a row.
    pick_unmatched: objects whose template fit was rejected are still offered to the planner as boxes / plates
    from their measured oriented box (`PlanOptions.pick_unmatched`); off, they are clutter only.
    reuse_fits: an instance whose mask and depth did not change since the previous frame of the scene (change
    detection on the new frame, see `reuse_iou` / `reuse_depth_m`) keeps its accepted fit instead of being fitted
    again. reuse_iou: mask IoU with the previous instance needed; reuse_depth_m: largest median depth change over
    the mask and over each of its halves, metres.
    perception_retries: when the planner finds no feasible grasp, the cell captures this many fresh frames (new
    sensor noise, everything fitted anew) before it gives up on the scene with a 'no_feasible_grasp' failure.
    plan_evaluation: the planner's candidate evaluation settings. relaxed_plan: before a retry, the same frame is
    planned again with `relaxed_evaluation` (riskier grasps: no extra noise margin around the other parts, jaw
    tips raised further off the floor); physics judges them. max_nudges: when still no grasp is found, the cell
    may push a part this many times per pick (`planning.push.plan_push` on the perceived scene,
    `sim.physics_push` on the true one) by `nudge_m` metres and perceive again, before the retries; with `drags`,
    a part near a wall (where a push cannot get behind it) is first dragged `drag_m` metres away from it
    (`planning.drag`). Every push and drag is carried
    out by an arm motion planned and judged like a pick's (`planning.push.judged_push_motion`: collision-checked,
    within the cell's joint, speed and workspace caps); of the `nudge_candidates` best drags (then pushes), the
    first with such a motion is made.
    uncovered: surfaces no instance covers are obstacles for the planner (`measure.uncovered`, as `process_frame`
    does); False: only what was segmented.
    clutter / stack_layers: scene composition (see sim.scene.SceneOptions).
    gripper: preset or packaged gripper name overriding the cell's tool for physics ('' = the cell's tool).
    resolution: (W, H) image size, pixels. physics: physics options.
    library: part libraries (templates.library.resolve_library entries: folders or 'builtin'; empty = the built-in
    parts); `parts` names parts of it.
    """

    cell_path: str
    sensor: str = "d435"
    seed: int = 0
    parts: tuple[str, ...] = ()
    parts_per_scene: int = 8
    segmenter: str = "model"
    renderer: str = "auto"
    match_iou: float = 0.5
    wrong_fit_m: float = 0.005
    max_consecutive_failures: int = 3
    pick_unmatched: bool = True
    reuse_fits: bool = True
    reuse_iou: float = 0.95
    reuse_depth_m: float = 0.0015
    perception_retries: int = 1
    plan_evaluation: EvaluationOptions = field(default_factory=EvaluationOptions)
    relaxed_plan: bool = True
    max_nudges: int = 2
    nudge_m: float = 0.05
    drags: bool = True
    uncovered: bool = True
    drag_m: float = 0.08
    nudge_candidates: int = 4
    relaxed_evaluation: EvaluationOptions = field(
        default_factory=lambda: EvaluationOptions(noise_margin=False, max_raise_m=0.03)
    )
    clutter: float = 0.3
    stack_layers: int = 2
    gripper: str = ""
    resolution: tuple[int, int] = (640, 480)
    physics: PhysicsOptions = field(default_factory=PhysicsOptions)
    library: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.segmenter not in SEGMENTERS:
            raise InputError(f"segmenter must be one of {SEGMENTERS}, got {self.segmenter!r}")
        if self.parts_per_scene < 1:
            raise InputError(f"parts_per_scene must be >= 1, got {self.parts_per_scene}")
        if self.perception_retries < 0:
            raise InputError(f"perception_retries must be >= 0, got {self.perception_retries}")
        if not 0.0 < self.reuse_iou <= 1.0 or not self.reuse_depth_m > 0.0:
            raise InputError(
                f"reuse_iou must be in (0, 1] and reuse_depth_m > 0, got {self.reuse_iou}, {self.reuse_depth_m}"
            )
        object.__setattr__(self, "parts", tuple(self.parts))


@dataclass(frozen=True)
class PickRecord:
    """One attempted pick (one CSV row). success: the part was lifted and held. cause: '' or one of CAUSES.
    part: true part name picked ('' when the grasp matched none); template: fitted template name.
    depth_m: height of the part's centre above the bin floor; occlusion: 1 - visible share of its silhouette.
    fit_error_m: mean symmetric closest-point distance of the fitted vs true model points (nan when unknown).
    physics: physics outcome ('' when not simulated). captures: frames captured for this pick (1 + perception
    retries used); fitted / reused: instances fitted anew / whose previous fit was kept (change detection);
    nudges: pushes made before this pick (nudge_collisions of them hit the cell; drags of them were drags).
    detail: the failure's finer cause (`simulate.trace`: the commonest rejection reason, the physics outcome, what
    the hand hit, ...); picture: the failure's picture, relative to the run folder ('' for a held pick).
    grasp_id: the chosen grasp's id (the plan's candidate; '' when no grasp was chosen); kind: what produced it
    (`grasp_kind`, one of KINDS; ''); plan_pass: the planner's pass that found it (`PickPlan.planning_pass`:
    'first', 'turned', 'leaned'; ''); relaxed: planned with simulate's relaxed margins (`relaxed_evaluation`);
    predicted_success: the grip mechanics' predicted success of the grasp (`planning.plan.predicted_success`, with
    the options it was planned with; nan when no grasp was chosen). Times in milliseconds."""

    scene: int
    pick: int
    success: bool
    cause: str
    part: str
    template: str
    scheme: str
    physics: str
    reason: str
    depth_m: float
    occlusion: float
    fit_error_m: float
    slip_m: float
    lift_m: float
    parts_left: int
    captures: int
    fitted: int
    reused: int
    nudges: int
    nudge_collisions: int
    pipeline_ms: float
    physics_ms: float
    detail: str = ""
    picture: str = ""
    drags: int = 0
    grasp_id: str = ""
    kind: str = ""
    plan_pass: str = ""
    relaxed: bool = False
    predicted_success: float = float("nan")

    def row(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in self.__dict__.items():
            out[key] = round(value, 6) if isinstance(value, float) else value
        return out


@dataclass(frozen=True)
class GraspOrigin:
    """Where a pick's chosen grasp came from (the `PickRecord` fields of the same names)."""

    grasp_id: str
    kind: str
    plan_pass: str
    relaxed: bool
    predicted_success: float


def grasp_kind(plan_pass: str, relaxed: bool, manipulation: str) -> str:
    """The one kind (of KINDS) a pick's grasp is counted under: the last manipulation made for the pick ('drag',
    'push': the part was moved before the grasp was planned), else 'relaxed' when simulate's relaxed-margin pass
    planned it, else the planner's pass (`PickPlan.planning_pass`). The parts are kept apart in `PickRecord`."""
    kind = manipulation or ("relaxed" if relaxed else plan_pass)
    if kind not in KINDS:
        raise ValueError(f"grasp kind {kind!r} (pass {plan_pass!r}, manipulation {manipulation!r}) is not in {KINDS}")
    return kind


@dataclass(frozen=True)
class SceneResult:
    """All picks of one scene; n_parts: parts in the scene at the start; cleared: bin empty at the end;
    parts_left: parts still in the bin at the end (parts knocked out of the bin are neither picked nor left).
    left: the trace of each part left (`simulate.trace.LeftPart`). pictures: (relative path, PNG bytes) of the
    failure pictures the records name (written next to the scene's file, not part of it)."""

    scene: int
    n_parts: int
    cleared: bool
    picks: tuple[PickRecord, ...]
    parts_left: int = 0
    left: tuple[LeftPart, ...] = ()
    pictures: tuple[tuple[str, bytes], ...] = field(default=(), compare=False, repr=False)


def scene_seed(seed: int, scene_index: int) -> int:
    """The composition seed of scene `scene_index` of a batch seeded `seed`."""
    return int(np.random.SeedSequence([int(seed), int(scene_index), 0x51D]).generate_state(1)[0])


PHYSICS_PRESETS = PRESETS


def gripper_spec(cell: Any, override: str) -> GripperSpec:
    """The physics model of the cell's gripper (its first tool), or of `override` (a packaged gripper or a preset
    name; one-tool cells only)."""
    if override and len(getattr(cell, "tools", ())) > 1:
        raise InputError(
            f"--gripper replaces a one-tool cell's gripper; cell {cell.name!r} has {len(cell.tools)} tools "
            f"({', '.join(t.name for t in cell.tools)}): leave --gripper out"
        )
    return tool_spec(cell.tool, override)


def gripper_specs(cell: Any, override: str) -> dict[str, GripperSpec]:
    """The physics model of each of the cell's tools by name (`tool_spec`); a plan is replayed with its tool's."""
    gripper_spec(cell, override)  # refuses --gripper on a dual-tool cell
    return {t.name: tool_spec(t, override) for t in cell.tools}


def _world_from_bin(cell: Any) -> FloatArray:
    """The cell's bin pose (centre of the inner floor); simulate needs a cell with a bin to fill with parts."""
    if cell.bin is None:
        raise InputError(f"cell {cell.name!r} has no bin; simulate needs a cell with a bin to fill with parts")
    return np.asarray(cell.bin.world_from_bin, dtype=np.float64)


def _fit_error(fitted: FloatArray, true: FloatArray, samples: FloatArray) -> float:
    """Mean closest-point distance between the model points at the fitted and at the true pose (ADD-S), m."""
    from scipy.spatial import cKDTree

    a = transform_points(fitted, samples)
    b = transform_points(true, samples)
    d, _ = cKDTree(b).query(a)
    return float(np.mean(d))


@dataclass(frozen=True, eq=False)
class _Setup:
    """What every scene of a batch shares in one process (built once: the library's templates keep their prepared
    fitting data, grasp synthesis and convex decompositions, which are cached by template identity)."""

    cell: Any
    library: tuple[Template, ...]
    spec: GripperSpec  # the first tool's (pushes and drags)
    specs: dict[str, GripperSpec]  # each tool's by name: a pick is replayed with its plan's tool
    sensor: Any
    camera: Any
    samples: dict[str, FloatArray]


_SETUPS: dict[tuple[Any, ...], _Setup] = {}
_SEGMENTERS: dict[tuple[str, tuple[str, ...]], Any] = {}


def _segmenter(kind: str, library: tuple[str, ...] = ()) -> Any:
    """The process's segmenter of `kind` ('model' or 'depth') for the part libraries `library` (a 'model' is the
    one stored with them, `perception.factory.library_model`, else the bundled one), created once (the ONNX
    session is reused)."""
    hit = _SEGMENTERS.get((kind, library))
    if hit is None:
        from normpos_grasp.perception.factory import library_model
        from normpos_grasp.pipeline import make_segmenter

        model = library_model(library) if kind == "model" else None
        hit = _SEGMENTERS[(kind, library)] = make_segmenter(kind, model)
    return hit


def _setup(config: SimulationConfig) -> _Setup:
    from normpos_grasp.cell.config import load_cell
    from normpos_grasp.sim.cameras import camera_intrinsics
    from normpos_grasp.sim.sensor import sensor_preset
    from normpos_grasp.templates.library import resolve_library

    path = Path(config.cell_path).resolve()
    key = (
        str(path),
        path.stat().st_mtime_ns if path.exists() else 0,
        config.gripper,
        config.sensor,
        config.resolution,
        config.library,
    )
    hit = _SETUPS.get(key)
    if hit is not None:
        return hit
    cell = load_cell(path)
    _world_from_bin(cell)
    wrist = cell.wrist_camera
    if cell.world_from_camera is None and wrist is None:
        raise InputError(f"cell {cell.name!r} has no camera pose; simulate renders through the cell's camera")
    library = tuple(resolve_library(config.library))
    world_from_camera = (
        cell.world_from_camera
        if wrist is None
        else wrist.world_from_camera(cell.world_from_base, cell.robot_model, wrist.capture_q[0])
    )
    camera = camera_intrinsics(config.sensor, config.resolution).with_extrinsics(world_from_camera)
    setup = _Setup(
        cell=cell,
        library=library,
        spec=gripper_spec(cell, config.gripper),
        specs=gripper_specs(cell, config.gripper),
        sensor=sensor_preset(config.sensor),
        camera=camera,
        samples={t.name: _model_points(t) for t in library},
    )
    _SETUPS[key] = setup
    return setup


@dataclass(frozen=True, eq=False)
class _Perception:
    """One captured frame (with its ground truth) and what the pipeline made of it."""

    frame: Any  # sim.dataset.SyntheticFrame
    result: FrameResult

    @property
    def instances(self) -> list[Any]:
        return self.result.instances

    @property
    def normpositions(self) -> list[Any]:
        return self.result.normpositions

    @property
    def fits(self) -> list[Any]:
        return self.result.fits


def _perceive(
    setup: _Setup,
    config: SimulationConfig,
    layout: Any,
    rng: np.random.Generator,
    scene_index: int,
    im_id: int,
    previous: _Perception | None,
    world_from_camera: FloatArray | None = None,
) -> _Perception:
    """Render the scene as it stands with sensor noise (from `world_from_camera` when given: a wrist camera at its
    capture pose), then the product's perception (`pipeline.perceive`: segment, measure, fit), keeping the accepted
    fits of objects that did not move since `previous`."""
    from normpos_grasp.sim.dataset import render_frame
    from normpos_grasp.sim.render import make_renderer

    camera = setup.camera if world_from_camera is None else setup.camera.with_extrinsics(world_from_camera)
    renderer = make_renderer(layout, camera.width, camera.height, config.renderer)
    try:
        frame = render_frame(layout, renderer, camera, setup.sensor, rng, scene_id=scene_index, im_id=im_id)
    finally:
        renderer.close()
    ideal = list(frame.instances) if config.segmenter == "gt" else None
    segmenter = None if ideal is not None else _segmenter(config.segmenter, config.library)
    options = PipelineOptions(
        measure=MeasureOptions(skip_failed=True),
        fit_workers=1,  # one scene per core already
        reuse=ReuseOptions(config.reuse_iou, config.reuse_depth_m),
    )
    result = perceive(
        frame.frame, segmenter, setup.library, options, ideal, previous.result if previous is not None else None
    )
    return _Perception(frame, result)


def run_scene(config: SimulationConfig, scene_index: int) -> SceneResult:
    """Simulate clearing scene `scene_index` of the batch described by `config` (see module docstring)."""
    from normpos_grasp.measure.uncovered import uncovered_points
    from normpos_grasp.planning.capture import plan_capture_move
    from normpos_grasp.planning.plan import PlanOptions, plan_pick
    from normpos_grasp.sim.scene import SceneOptions, compose_scene

    setup = _setup(config)
    cell = setup.cell
    library = list(setup.library)
    spec = setup.spec
    rng = np.random.default_rng(np.random.SeedSequence([int(config.seed), int(scene_index), 0xF4A]))
    b = cell.bin
    if b is None:  # checked by _setup; narrows the type
        raise InputError("simulate needs a cell with a bin")
    options = SceneOptions(
        parts=config.parts,
        count=config.parts_per_scene,
        container="bin",
        bin_inner_size_m=(float(b.inner_size[0]), float(b.inner_size[1])),
        bin_wall_height_m=float(b.inner_size[2]),
        bin_wall_thickness_m=float(b.wall_m),
        bin_floor_thickness_m=float(b.wall_m),
        clutter=config.clutter,
        stack_layers=config.stack_layers,
        seed=scene_seed(config.seed, scene_index),
    )
    layout = compose_scene(options, library)
    cell_from_scene = _world_from_bin(cell) @ np.linalg.inv(_floor_pose(layout))
    templates = list(layout.templates)
    poses = np.array([cell_from_scene @ p for p in layout.world_from_object]).reshape(-1, 4, 4)
    statics = tuple((name, cell_from_scene @ pose, np.asarray(size)) for name, pose, size in layout.static_boxes)
    floor_z = float((cell_from_scene @ _floor_pose(layout))[2, 3])
    plan_options = PlanOptions(pick_unmatched=config.pick_unmatched, evaluation=config.plan_evaluation)
    physics_opts = replace(config.physics, lift_to_z_m=float(cell.entry_z) + config.physics.approach_m)
    samples = setup.samples
    n_start = len(templates)
    records: list[PickRecord] = []
    pictures: list[tuple[str, bytes]] = []
    left: list[LeftPart] = []
    failures = 0
    pick = 0
    im_id = 0
    previous: _Perception | None = None
    max_picks = 3 * n_start + 3
    wrist = cell.wrist_camera
    arm_q = np.asarray(cell.home_q, dtype=np.float64)  # where the arm stands (a wrist camera moves it to capture)
    while templates and pick < max_picks and failures < config.max_consecutive_failures:
        t0 = time.perf_counter()
        view = 0  # the wrist camera's capture pose: the first, then the next one for each retry
        captures = fitted = reused = nudges = hits = drags = 0
        manipulation = ""  # the last nudge made for this pick ('drag' or 'push')
        relaxed_used = False  # the plan came from the relaxed-margin pass
        retries_left, nudges_left = config.perception_retries, config.max_nudges
        last = previous if config.reuse_fits else None
        blocked = ""  # why the arm could not reach the capture pose
        while True:
            current = replace(layout, templates=tuple(templates), world_from_object=poses, static_boxes=statics)
            start_q, world_from_camera = None, None
            if wrist is not None:
                try:
                    move = plan_capture_move(cell, arm_q, view)
                except NormposError as exc:
                    blocked = str(exc)
                    break
                arm_q = start_q = move.capture_q
                world_from_camera = move.world_from_camera
            seen = _perceive(setup, config, current, rng, scene_index, im_id, last, world_from_camera)
            im_id += 1
            captures += 1
            fitted += len(seen.fits) - seen.result.reused_fits
            reused += seen.result.reused_fits
            uncovered = (
                uncovered_points(seen.frame.frame, [i.mask for i in seen.instances], cell.bins)
                if config.uncovered
                else None
            )
            plan = plan_pick(seen.fits, seen.normpositions, cell, plan_options, start_q, uncovered)
            relaxed_used = False
            if plan.status != "ok" and config.relaxed_plan:
                relaxed = replace(plan_options, evaluation=config.relaxed_evaluation)
                second = plan_pick(seen.fits, seen.normpositions, cell, relaxed, start_q, uncovered)
                if second.status == "ok":
                    plan, relaxed_used = second, True
            if plan.status == "ok" and plan.chosen is not None:
                break
            nudge = None
            if nudges_left > 0:
                nudge, nudge_q = _planned_nudge(plan, seen, cell, spec, floor_z, config, arm_q)
            if nudge is not None:
                from normpos_grasp.sim.physics_push import PushOptions, simulate_push

                pushed = simulate_push(
                    list(zip(templates, poses, strict=True)), statics, spec, nudge.world_from_tcp, nudge.push,
                    PushOptions(physics=config.physics),
                )  # fmt: skip
                nudges_left -= 1
                nudges += 1
                drags += int(nudge.kind == "drag")
                manipulation = nudge.kind
                hits += int(pushed.outcome == "collision")
                arm_q = nudge_q  # the arm carried the push out: it stands where the motion ended
                keep = [j for j in range(len(templates)) if _in_bin(pushed.world_from_objects_final[j], cell, floor_z)]
                templates = [templates[j] for j in keep]
                poses = pushed.world_from_objects_final[keep].reshape(-1, 4, 4)
                last = seen if config.reuse_fits else None  # change detection finds what the push moved
                if templates:
                    continue
                break
            if retries_left > 0:
                # a retry captures a fresh frame and fits everything anew (the kept fits led to no grasp), with a
                # wrist camera from its next capture pose
                retries_left -= 1
                last = None
                if wrist is not None:
                    view = (view + 1) % len(wrist.capture_q)
                continue
            break
        if blocked:
            records.append(
                _record(
                    scene_index, pick, "no_feasible_grasp", "", "", "", None, np.nan, np.nan, np.nan, len(templates),
                    (captures, fitted, reused, nudges, hits, drags), (time.perf_counter() - t0) * 1e3, 0.0, blocked,
                    "capture_move",
                )
            )  # fmt: skip
            left = [LeftPart(t.name, "path", "no capture move") for t in templates]
            break
        previous = seen
        frame, instances, fits = seen.frame, seen.instances, seen.fits
        counts = (captures, fitted, reused, nudges, hits, drags)
        if not templates:  # a push knocked the last parts out of the bin: nothing left to pick
            break
        pipeline_ms = (time.perf_counter() - t0) * 1e3
        visib = np.asarray(frame.visib_fractions, dtype=np.float64)
        if plan.status != "ok" or plan.chosen is None:
            # the parts left, each with its commonest rejections and its closest call
            reason = stop_line(plan) if plan.targets else _no_grasp_reason(plan.counts)
            if not instances:
                cause, reason = "segmentation_miss", "the segmenter found no instance"
            elif not any(f.accepted for f in fits) and not plan.targets:
                rejected = sorted({f.reason.split(";")[0] for f in fits if f.reason})[:2]
                cause, reason = "wrong_fit", "no template fit accepted: " + "; ".join(rejected)
            else:
                cause = "no_feasible_grasp"
            detail = (
                "no instance"
                if cause == "segmentation_miss"
                else (_short_reason(reason) if cause == "wrong_fit" else dominant_reason(plan.counts))
            )
            closest = [(r.best_world_from_tcp, r.best_opening_m) for r in rejections_by_target(plan)]
            name = _picture_name(scene_index, pick)
            pictures.append(
                (name, _picture(seen, list(zip(templates, poses, strict=True)), closest, f"{cause}: {reason}"))
            )
            records.append(
                _record(
                    scene_index, pick, cause, "", "", "", None, np.nan, np.nan, np.nan, len(templates), counts,
                    pipeline_ms, 0.0, reason, detail, name,
                )
            )  # fmt: skip
            left = left_parts(
                [t.name for t in seen.frame.layout.templates], list(seen.frame.rendering.masks_visible),
                instances, fits, plan if plan.targets else None, config.match_iou,
            )  # fmt: skip
            break
        cand = plan.chosen.candidate
        target = plan.targets[cand.target]
        used = replace(plan_options, evaluation=config.relaxed_evaluation) if relaxed_used else plan_options
        origin = GraspOrigin(
            cand.grasp_id,
            grasp_kind(plan.planning_pass, relaxed_used, manipulation),
            plan.planning_pass,
            relaxed_used,
            predicted_success(plan, used),
        )
        if plan.waypoints:  # the arm carries the plan out whatever physics says: the next capture move starts there
            arm_q = np.asarray(plan.waypoints[-1].q, dtype=np.float64)
        inst = next((i for i in instances if i.instance_id == target.instance_id), None)
        ious = [mask_iou(inst.mask, m) for m in frame.rendering.masks_visible] if inst is not None else []
        k = int(np.argmax(ious)) if ious else -1
        matched = k >= 0 and ious[k] >= config.match_iou
        chosen = [(cand.world_from_tcp, float(cand.opening_m))]
        if k < 0 or ious[k] <= 0.0:
            name = _picture_name(scene_index, pick)
            pictures.append((name, _picture(seen, [], chosen, "segmentation_miss: the chosen instance covers no part")))
            records.append(
                _record(
                    scene_index, pick, "segmentation_miss", "", target.template, cand.scheme, None, np.nan, np.nan,
                    np.nan, len(templates), counts, pipeline_ms, 0.0, "the chosen instance covers no part",
                    "chosen instance covers no part", name, origin,
                )
            )  # fmt: skip
            failures += 1
            pick += 1
            continue
        true_pose = poses[k]
        if target.template == templates[k].name:
            pts = samples.get(templates[k].name)
            pts = _model_points(templates[k]) if pts is None else pts
            fit_err = _fit_error(np.asarray(target.world_from_object), true_pose, pts)
        else:
            fit_err = float("inf")  # the wrong template was fitted (or none: a primitive box of the measurement)
        neighbours = [(templates[j], poses[j]) for j in range(len(templates)) if j != k]
        t1 = time.perf_counter()
        hand = setup.specs.get(plan.tool.name, spec)  # the chosen tool's (cup or jaws) on a dual-tool flange
        result = validate_grasp(
            templates[k],
            true_pose,
            neighbours,
            statics,
            hand,
            cand.world_from_tcp,
            max(float(cand.opening_m), 1e-3) if hand.kind == "parallel" else 0.0,
            physics_opts,
        )
        physics_ms = (time.perf_counter() - t1) * 1e3
        depth = float(true_pose[2, 3] - floor_z)
        occlusion = float(1.0 - visib[k]) if k < len(visib) else float("nan")
        if result.success:
            cause = ""
        elif not matched:
            cause = "segmentation_miss"
        elif fit_err > config.wrong_fit_m:
            cause = "wrong_fit"
        elif result.outcome == "collision":
            cause = "collision"
        else:
            cause = "physics_drop"
        others = [j for j in range(len(templates)) if j != k]
        # parts the hand took out with the target (clamped beside it, or lying on it): they go to the place with it
        carried = (
            [others[n] for n in carried_out(poses[others], result.world_from_neighbours_final, result.lift_m)]
            if result.success
            else []
        )
        detail, name = "", ""
        if carried:
            detail = "also carried out: " + ", ".join(templates[j].name for j in carried)
        if cause:
            detail = _failure_detail(cause, result, target.template == templates[k].name)
            name = _picture_name(scene_index, pick)
            caption = f"{cause} ({detail}): {result.reason}; fit {target.template} vs true {templates[k].name}"
            pictures.append((name, _picture(seen, [(templates[k], true_pose)], chosen, caption)))
        records.append(
            _record(
                scene_index, pick, cause, templates[k].name, target.template, cand.scheme, result, depth, occlusion,
                fit_err, len(templates), counts, pipeline_ms, physics_ms, result.reason, detail, name, origin,
            )
        )  # fmt: skip
        # the scene as physics left it, less what left with the hand
        new_poses = {j: result.world_from_neighbours_final[n] for n, j in enumerate(others) if j not in carried}
        if not result.success:
            new_poses[k] = result.world_from_object_final
            failures += 1
        else:
            failures = 0
        keep = [j for j in sorted(new_poses) if _in_bin(new_poses[j], cell, floor_z)]
        templates = [templates[j] for j in keep]
        poses = np.array([new_poses[j] for j in keep]).reshape(-1, 4, 4)
        pick += 1
    if templates and not left:  # the scene ran out of picks: every part left is traced to the stop
        last_cause = next((r.cause for r in reversed(records) if r.cause), "")
        why = (
            f"after {failures} failed picks in a row (last {last_cause})"
            if failures >= config.max_consecutive_failures
            else "the most picks allowed"
        )
        left = [LeftPart(t.name, "stopped", why) for t in templates]
    return SceneResult(
        scene_index, n_start, not templates, tuple(records), len(templates), tuple(left), tuple(pictures)
    )


def _planned_nudge(
    plan: Any,
    seen: _Perception,
    cell: Any,
    spec: GripperSpec,
    floor_z: float,
    config: SimulationConfig,
    arm_q: FloatArray,
) -> tuple[Push | None, FloatArray]:
    """The first of the best drags (parts near a wall), then pushes, whose arm motion from `arm_q` is planned and
    passes the cell's judge; with the joints the motion ends at. (None, arm_q) when none has one."""
    import itertools

    from normpos_grasp.errors import PlanningError
    from normpos_grasp.planning.drag import drag_candidates
    from normpos_grasp.planning.push import judged_push_motion, push_candidates

    hand = PushHand(spec.tip_beyond_tcp_m, spec.finger_width_m, spec.finger_thickness_m)
    args = (plan, seen.fits, seen.normpositions, cell, hand, floor_z, config.nudge_m)
    n = config.nudge_candidates
    tries = [itertools.islice(push_candidates(*args), n)]
    if config.drags:  # a part against a wall is dragged away from it first: a push cannot get behind it
        tries.insert(
            0, itertools.islice(drag_candidates(plan, seen.fits, seen.normpositions, cell, floor_z, config.drag_m), n)
        )
    for candidate in itertools.chain(*tries):
        try:
            motion = judged_push_motion(candidate, seen.fits, seen.normpositions, cell, arm_q)
        except PlanningError as exc:
            logger.debug("%s refused: %s", candidate.kind, exc)
            continue
        return candidate, np.asarray(motion.q[-1], dtype=np.float64)
    return None, arm_q


def _picture_name(scene: int, pick: int) -> str:
    """The run-folder path of a failed pick's picture."""
    return f"failures/scene_{scene:06d}_pick_{pick:02d}.png"


def _picture(
    seen: _Perception,
    true_parts: list[tuple[Template, FloatArray]],
    grasps: list[tuple[FloatArray, float]],
    caption: str,
) -> bytes:
    return failure_picture(seen.frame.frame, seen.instances, seen.fits, true_parts, grasps, caption)


def _short_reason(reason: str) -> str:
    """A reason without its figures (one row of the cause table for every pick it explains)."""
    import re

    text = re.sub(r"[-+]?\d[\d.]*(e[-+]?\d+)?", "#", reason.split(";")[0])
    return text.strip()[:60]


def _failure_detail(cause: str, result: PhysicsResult, same_template: bool) -> str:
    """The finer cause of a pick physics judged (see `simulate.trace`)."""
    if cause == "segmentation_miss":
        return f"mask IoU below the match, then {result.outcome}"
    if cause == "wrong_fit":
        what = "wrong template" if not same_template else "pose off the true one"
        return f"{what}, then {result.outcome}"
    if cause == "collision":
        hit = result.collision_with or "?"
        import re

        hit = re.sub(r"_g\d+$", "", hit)
        return "hit a neighbour part" if re.match(r"nb\d+$", hit) else f"hit {hit}"
    return result.outcome


def _no_grasp_reason(counts: dict[str, int]) -> str:
    """'no feasible grasp' with the three most frequent rejection reasons of the planner."""
    top = sorted(((n, r) for r, n in counts.items() if r != "not_evaluated"), reverse=True)[:3]
    detail = ", ".join(f"{r} {n}" for n, r in top)
    return f"no feasible grasp ({detail})" if detail else "no feasible grasp (no candidates)"


def _model_points(template: Template, n: int = 500) -> FloatArray:
    """(n, 3) surface samples of a template (deterministic), metres."""
    import trimesh

    pts, _ = trimesh.sample.sample_surface_even(template.mesh, n, seed=0)
    return np.asarray(pts, dtype=np.float64)


def _floor_pose(layout: Any) -> FloatArray:
    """Pose (scene frame) of the bin floor's top centre."""
    centre = np.asarray(layout.container_centre(), dtype=np.float64)
    return make_pose(None, centre)


def carried_out(before: FloatArray, after: FloatArray, lift_m: float) -> list[int]:
    """Indices of the neighbours (poses (K, 4, 4) before and after a held pick) that rose with the hand by more
    than half the target's lift `lift_m` (m; physics' own test of a lifted target): clamped between the jaws beside
    the target or lying on it, they leave the bin with it. Left at their last pose they would hang in the air where
    the physics run ended, and the next pick would be judged on a part falling from there."""
    rise = (
        np.asarray(after, dtype=np.float64).reshape(-1, 4, 4)[:, 2, 3]
        - np.asarray(before, dtype=np.float64).reshape(-1, 4, 4)[:, 2, 3]
    )
    if not lift_m > 0.0:
        return []
    return [int(j) for j in np.flatnonzero(rise > 0.5 * lift_m)]


def _in_bin(pose: FloatArray, cell: Any, floor_z: float) -> bool:
    """Whether a part's origin still lies inside the bin's inner volume (parts that fell out leave the scene)."""
    b = cell.bin
    bin_pose = np.asarray(b.world_from_bin, dtype=np.float64)
    local = np.linalg.inv(bin_pose) @ np.append(pose[:3, 3], 1.0)
    inner = np.asarray(b.inner_size, dtype=np.float64)
    return bool(abs(local[0]) <= inner[0] / 2.0 and abs(local[1]) <= inner[1] / 2.0 and pose[2, 3] >= floor_z - 0.02)


def _record(
    scene: int,
    pick: int,
    cause: str,
    part: str,
    template: str,
    scheme: str,
    result: PhysicsResult | None,
    depth: float,
    occlusion: float,
    fit_err: float,
    parts_left: int,
    counts: tuple[int, ...],
    pipeline_ms: float,
    physics_ms: float,
    reason: str,
    detail: str = "",
    picture: str = "",
    origin: GraspOrigin | None = None,
) -> PickRecord:
    return PickRecord(
        scene=scene,
        pick=pick,
        success=result is not None and result.success,
        cause=cause,
        part=part,
        template=template,
        scheme=scheme,
        physics=result.outcome if result is not None else "",
        reason=reason,
        depth_m=float(depth),
        occlusion=float(occlusion),
        fit_error_m=float(fit_err),
        slip_m=float(result.slip_m) if result is not None else float("nan"),
        lift_m=float(result.lift_m) if result is not None else float("nan"),
        parts_left=parts_left,
        captures=counts[0],
        fitted=counts[1],
        reused=counts[2],
        nudges=counts[3],
        nudge_collisions=counts[4],
        drags=counts[5],
        pipeline_ms=float(pipeline_ms),
        physics_ms=float(physics_ms),
        detail=detail,
        picture=picture,
        grasp_id=origin.grasp_id if origin is not None else "",
        kind=origin.kind if origin is not None else "",
        plan_pass=origin.plan_pass if origin is not None else "",
        relaxed=origin.relaxed if origin is not None else False,
        predicted_success=float(origin.predicted_success) if origin is not None else float("nan"),
    )
