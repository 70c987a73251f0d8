"""Pick-and-place planning: from accepted template fits and measured norm-positions to a `PickPlan`.

home -> entry -> pre_grasp -> grasp -> lift -> retreat -> pre_place -> place -> post_place. Approach and retreat
are Cartesian straight lines (dense IK on one analytic branch); the transfers (home -> entry, retreat -> pre_place)
are joint-space motions, straight when collision-free, otherwise RRT-Connect. The whole path is time-parameterised
within the cell's caps. Before a plan is returned, the cell's judge (`cell.limits.SafetyLimits.from_cell(cell)
.check_path`, the check `execution.plan.check_plan` runs) passes its waypoints, the straight joint segments between
them and its timed samples; a plan it refuses is a rejected grasp (reason 'path_cell_<check>' or, for a place
branch, 'place_cell_<check>') and the next branch or grasp is tried. The servo commands execution would stream for
the plan pass the driver's check too (`cell.stream.check_stream`): a plan whose stream exceeds a cap is re-timed
with the jerk cap halved, down to a floor, else rejected ('path_stream_<check>'; `_timed_for_stream`). No feasible
grasp is a result (status 'no_feasible_grasp' with reason counts), not an error.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from normpos_grasp.cell.config import CellConfig, PlaceSpec
from normpos_grasp.cell.limits import SafetyLimits
from normpos_grasp.cell.stream import check_stream, stream_cuts
from normpos_grasp.collision.world import CollisionWorld
from normpos_grasp.errors import PlanningError, SafetyViolation
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.grasp.candidates import (
    CandidateOptions,
    candidates_for_object,
    primitive_template,
    symmetry_axes_world,
)
from normpos_grasp.grasp.lean import LeanOptions, wall_leans
from normpos_grasp.grasp.quality import judge
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.planning.branches import half_turn_symmetric, place_poses, quickest_grasp, ranked_place_configs
from normpos_grasp.planning.evaluate import EvaluationOptions, evaluate_candidates, within_stroke
from normpos_grasp.planning.rrt import MotionOptions, plan_joint_motion
from normpos_grasp.planning.timing import PathPiece, TimingOptions, joint_caps, time_parameterise, time_path
from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.plan import Evaluation, PickPlan, Target, Trajectory, Waypoint
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.records.tool import IDLE_PREFIX
from normpos_grasp.typing import BoolArray, FloatArray

logger = logging.getLogger(__name__)

WAYPOINTS = ("home", "entry", "pre_grasp", "grasp", "lift", "retreat", "pre_place", "place", "post_place")
#: the world's name of the clutter built from surfaces no instance covers (its voxels are UNCOVERED/<k>)
UNCOVERED = "clutter/uncovered"
#: `PickPlan.planning_pass` of a plan with a grasp, in the order `_plan_tool` runs the passes
PLANNING_PASSES = ("first", "turned", "leaned")


@dataclass(frozen=True)
class PlanOptions:
    """Planner settings.

    cartesian_step_m: sample spacing of straight-line segments, m. max_joint_jump_rad: largest joint change
    between two samples of a straight line before it counts as a branch flip. explain_tolerance_m: measured
    points farther than this outside their fitted template's box count as unexplained clutter, m.
    pick_unmatched: also pick objects that matched no template, as boxes/plates from their oriented box.
    place_drop_m: the held object's lowest point stays this far above the place surface at release, m.
    max_plan_attempts: ranked grasps tried for a full path before giving up.
    release_tolerance_m: over the first this-many metres of the lift the held object may graze other objects and
    clutter (fitted poses of touching parts overlap by pose noise); tool and arm are checked as always.
    clutter_min_points: measured points no fit explains become clutter only where at least this many of them (the
    point itself included) lie within the cell's voxel size: lone points are sensor outliers (flying pixels at
    depth edges), not obstacles.
    neighbour_tolerance_m: points of one instance that lie inside ANOTHER accepted fit's template box grown by this
    much are that neighbour's (a mask that bled across the border between touching parts), not clutter, m.
    quickest_branches: reach the grasp with joint 6 turned by the quicker multiple of pi and place through the
    equivalent place pose and IK branch with the quickest estimated motion (`planning.branches`); False: the
    evaluation's joint angles and the place pose as given.
    leans: when no grasp is feasible, plan once more with the grasps the cell's boxes block at the grasp leaned
    away from them (`grasp.lean.wall_leans`: turned about the closing axis or the part's symmetry axis, or slid
    along the pads), every check as for any candidate; None: no such pass.
    """

    cartesian_step_m: float = 0.01
    max_joint_jump_rad: float = 0.35
    explain_tolerance_m: float = 0.01
    pick_unmatched: bool = False
    place_drop_m: float = 0.005
    release_tolerance_m: float = 0.01
    max_plan_attempts: int = 12
    clutter_min_points: int = 3
    neighbour_tolerance_m: float = 0.003
    quickest_branches: bool = True
    candidates: CandidateOptions = CandidateOptions()
    evaluation: EvaluationOptions = EvaluationOptions()
    motion: MotionOptions = MotionOptions()
    timing: TimingOptions = TimingOptions()
    leans: LeanOptions | None = LeanOptions()


def build_world(
    cell: CellConfig,
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition],
    arm: ArmModel,
    options: PlanOptions | None = None,
    uncovered: FloatArray | None = None,
) -> tuple[CollisionWorld, list[Target], list[Any]]:
    """The collision world of a frame and the pickable targets.

    Accepted fits become BVH meshes ('object/<k>'); measured points that no accepted fit explains become voxel
    boxes ('clutter'); with `pick_unmatched`, norm-positions without a fit become primitive targets instead.
    uncovered: (N, 3) world points of surfaces no instance covers (`measure.uncovered.uncovered_points`: what the
    segmenter missed); those no target's box (grown by `neighbour_tolerance_m`) explains become clutter too
    ('clutter/uncovered'). Returns (world, targets, templates per target)."""
    opts = options or PlanOptions()
    world = CollisionWorld()
    for box in cell.static_boxes:
        world.add_box(box.name, box.world_from_box, box.size, "cell")
    targets: list[Target] = []
    templates: list[Any] = []
    fitted_ids: set[int] = set()
    for k, fit in enumerate(fits):
        if not fit.accepted:
            continue
        if fit.frame != "world":
            raise PlanningError(
                f"fit {k} ({fit.template.name}) is in frame {fit.frame!r}; plan_pick needs world-frame "
                "fits: transform them with the camera's world_from_camera first"
            )
        mesh = fit.template.mesh
        if abs(fit.scale - 1.0) > 1e-6:
            mesh = mesh.copy()
            mesh.apply_scale(fit.scale)
        name = f"object/{k}"
        world.add_mesh(name, mesh, fit.world_from_object, "object")
        centre = fit.world_from_object[:3, :3] @ np.asarray(mesh.bounds).mean(axis=0) + fit.world_from_object[:3, 3]
        targets.append(
            Target(
                name,
                np.asarray(fit.world_from_object, dtype=np.float64),
                mesh,
                float(centre[2]),
                fit.template.mass_kg,
                fit.instance_id,
                fit.template.name,
            )
        )
        templates.append(fit.template)
        fitted_ids.add(fit.instance_id)
    for np_ in normpositions:
        if np_.frame != "world":
            raise PlanningError(
                f"norm-position {np_.instance_id} is in frame {np_.frame!r}; plan_pick needs the world frame"
            )
        pts = np.asarray(np_.points, dtype=np.float64)
        if np_.instance_id in fitted_ids:
            pts = _unexplained(pts, [t for t in targets if t.instance_id == np_.instance_id], opts.explain_tolerance_m)
        elif opts.pick_unmatched and np_.n_points >= 10:
            template, pose = primitive_template(np_)
            name = f"object/unmatched_{np_.instance_id}"
            world.add_mesh(name, template.mesh, pose, "object")
            targets.append(
                Target(
                    name,
                    pose,
                    template.mesh,
                    float(pose[2, 3]),
                    template.mass_kg,
                    np_.instance_id,
                    template.name,
                    measured_points=pts,
                )
            )
            templates.append(template)
            continue
        # a mask that bled over a touching neighbour: those points are explained by the neighbour's fit (left as
        # clutter they sit inside that part and block every lift of it)
        others = [t for t in targets if t.instance_id != np_.instance_id]
        if len(pts) and others:
            pts = _unexplained(pts, others, opts.neighbour_tolerance_m)
        pts = _drop_outliers(pts, cell.voxel_m, opts.clutter_min_points)
        if len(pts):
            world.add_points(f"clutter/{np_.instance_id}", pts, cell.voxel_m, "clutter")
    if uncovered is not None and len(uncovered):
        pts = _unexplained(np.asarray(uncovered, dtype=np.float64).reshape(-1, 3), targets, opts.neighbour_tolerance_m)
        pts = _drop_outliers(pts, cell.voxel_m, opts.clutter_min_points)
        if len(pts):
            world.add_points(UNCOVERED, pts, cell.voxel_m, "clutter")
    return world, targets, templates


def _uncovered_centres(world: CollisionWorld) -> FloatArray:
    """(K, 3) centres of the world's voxels built from surfaces no instance covers (`build_world`'s UNCOVERED), m."""
    boxes = [0.5 * (e.lo + e.hi) for name, e in world.elements.items() if name.startswith(UNCOVERED + "/")]
    return np.asarray(boxes, dtype=np.float64).reshape(-1, 3)


def _drop_outliers(points: FloatArray, radius_m: float, min_points: int) -> FloatArray:
    """Points (N, 3) with at least `min_points` points (themselves included) within `radius_m`.

    A point sharing its cell of edge radius_m / 2 (any two points in one are under 0.87 radius_m apart) with at least
    `min_points` points is kept without a query; only the others (about one in seven of a measured surface) are
    counted in the k-d tree of all points: the same points as counting every one."""
    if min_points <= 1 or len(points) == 0:
        return points
    from scipy.spatial import cKDTree

    cells = np.floor(points / (0.5 * radius_m)).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:  # cell keys would overflow: count every point
        counts = cKDTree(points).query_ball_point(points, radius_m, return_length=True)
        return points[np.asarray(counts) >= min_points]
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, inverse, per_cell = np.unique(key, return_inverse=True, return_counts=True)
    keep = per_cell[inverse] >= min_points
    rest = np.flatnonzero(~keep)
    if len(rest):
        counts = cKDTree(points).query_ball_point(points[rest], radius_m, return_length=True)
        keep[rest] = np.asarray(counts) >= min_points
    return points[keep]


def _unexplained(points: FloatArray, targets: list[Target], tol: float) -> FloatArray:
    """Points outside every target's template box grown by `tol` (object frame)."""
    keep = np.ones(len(points), dtype=bool)
    for t in targets:
        inv = invert_pose(t.world_from_object)
        local = points @ inv[:3, :3].T + inv[:3, 3]
        lo, hi = np.asarray(t.mesh.bounds)  # type: ignore[attr-defined]
        inside = np.all((local >= lo - tol) & (local <= hi + tol), axis=1)
        keep &= ~inside
    return points[keep]


def plan_pick(
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition],
    cell: CellConfig,
    options: PlanOptions | None = None,
    start_q: FloatArray | None = None,
    uncovered: FloatArray | None = None,
) -> PickPlan:
    """Choose an object and a grasp and plan the pick-and-place motion from `start_q` (default the cell's home).
    uncovered: measured points no instance covers (`measure.uncovered.uncovered_points`), obstacles where no
    target explains them (`build_world`).

    A cell with several bins (`cell.bins`): every bin's walls are in the collision world and every perceived part an
    obstacle; the parts are sorted into bins by their centre (`CellConfig.bin_of`; parts in no bin are not picked)
    and the bins are tried in turn from `cell.bin` on (`_plan_bins`): a part of bin B gets the candidates, the bin
    entry and exit height and the places of bin B only. The plan names its bin and the bins seen empty.

    A cell with several tools on its flange (`cell.tools`): the same frame is planned with each tool (the cell with
    that tool alone, `CellConfig.with_tool`; each tool's shapes hold the idle one's body) and the plan whose chosen
    grasp has the best predicted success (`grasp.quality.judge`), then the best ranking score, is kept; ties go to
    the earlier tool. The plan's `tool` is the one chosen. With no plan for any tool: the first tool's
    'no_feasible_grasp' plan with every tool's evaluations and rejection counts."""
    opts = options or PlanOptions()
    t_start = time.perf_counter()
    timing: dict[str, float] = {}
    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    world, targets, templates = build_world(cell, fits, normpositions, arm, opts, uncovered)
    n_uncovered = len(_uncovered_centres(world))
    world.set_arm(arm)
    timing["world"] = (time.perf_counter() - t_start) * 1e3
    home = np.asarray(cell.home_q if start_q is None else start_q, dtype=np.float64)
    plans = []
    for tool in cell.tools:
        one = cell if len(cell.tools) == 1 else cell.with_tool(tool)
        world.set_tool(tool)
        world.update()
        plans.append(_plan_tool(targets, templates, normpositions, world, arm, one, home, opts, dict(timing), t_start))
    plan = plans[0] if len(plans) == 1 else _best_tool_plan(plans, opts)
    return replace(plan, uncovered_voxels=n_uncovered) if n_uncovered else plan


def _plan_tool(
    targets: list[Target],
    templates: list[Any],
    normpositions: Sequence[NormPosition],
    world: CollisionWorld,
    arm: ArmModel,
    cell: CellConfig,
    home: FloatArray,
    opts: PlanOptions,
    timing: dict[str, float],
    t_start: float,
) -> PickPlan:
    """`plan_pick` with the world's tool set to `cell.tool` (the cell's only tool). A tool that holds an idle tool's
    body (a dual-tool flange: lopsided) without a plan is planned once more with every candidate turned about its
    approach axis (`_turned`: the same grasps with the idle body on another side); the turned copies go in a second
    pass so that they do not take the feasible slots of other grasps in the first. Still without a plan, the grasps
    the cell's boxes block are planned once more leaned away from them (`PlanOptions.leans`, `_plan_once`'s
    'leaned'). The plan's `planning_pass` names the pass that found its grasp ('' with none)."""
    plan = _plan_once(targets, templates, normpositions, world, arm, cell, home, opts, timing, t_start, "")
    if plan.status == "ok":
        return replace(plan, planning_pass="first")
    passes = []
    if any(s.name.startswith(IDLE_PREFIX) for s in cell.tool.shapes):
        passes.append("turned")
    if opts.leans is not None and cell.tool.kind == "parallel":
        passes.append("leaned")
    for variant in passes:
        again = _plan_once(targets, templates, normpositions, world, arm, cell, home, opts, timing, t_start, variant)
        if again.status == "ok":
            return replace(again, planning_pass=variant)
        counts = Counter(plan.counts)
        counts.update(again.counts)
        plan = replace(
            plan,
            evaluations=plan.evaluations + again.evaluations,
            counts=dict(counts),
            timing_ms={**again.timing_ms, "total": again.timing_ms.get("total", 0.0)},
        )
    return plan


def _plan_once(
    targets: list[Target],
    templates: list[Any],
    normpositions: Sequence[NormPosition],
    world: CollisionWorld,
    arm: ArmModel,
    cell: CellConfig,
    home: FloatArray,
    opts: PlanOptions,
    timing: dict[str, float],
    t_start: float,
    variant: str,
) -> PickPlan:
    """One planning pass of `_plan_tool`: the candidates as synthesised (`variant` ''), or only their turned copies
    ('turned', `_turned`) or their copies leaned away from the cell's boxes that block them ('leaned', `_leaned`)."""
    if len(cell.bins) > 1:
        return _plan_bins(
            targets, templates, normpositions, world, arm, cell, home, opts, dict(timing), t_start, variant
        )
    t0 = time.perf_counter()
    candidates: list[GraspCandidate] = []
    cand_opts = _candidate_options(cell, opts)
    # symmetric parts are also offered jaws closing along the bin's walls (palm parallel to the nearest wall)
    walls = cell.bin.world_from_bin[:3, :2].T.copy() if cell.bin is not None else None
    for k, (target, template) in enumerate(zip(targets, templates, strict=True)):
        found = candidates_for_object(k, template, target.world_from_object, cell.tool.kind, cand_opts, walls)
        candidates.extend(_variant(found, variant, k, template, target, world, cell, opts))
    timing = dict(timing)
    timing["candidates"] = (time.perf_counter() - t0) * 1e3
    return plan_from_candidates(candidates, targets, world, arm, cell, home, opts, timing, t_start)


#: turns about the TCP z axis offered for each candidate of a tool with an idle tool beside it (`_turned`)
_TURNS = {"parallel": (np.pi,), "suction": (np.pi / 2, np.pi, 3 * np.pi / 2)}


def _turned(candidates: list[GraspCandidate], cell: CellConfig) -> list[GraspCandidate]:
    """Each candidate turned about its approach axis (`@turn<k>` in the id): the jaws' half turn, the cup's quarter
    turns, the same grasp of the part with a tool's idle neighbour on another side (away from a wall or a part)."""
    out: list[GraspCandidate] = []
    for k, angle in enumerate(_TURNS[cell.tool.kind]):
        c, s = np.cos(angle), np.sin(angle)
        turn = np.array([[c, -s, 0.0, 0.0], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
        out.extend(
            replace(cand, grasp_id=f"{cand.grasp_id}@turn{k + 1}", world_from_tcp=cand.world_from_tcp @ turn)
            for cand in candidates
        )
    return out


def _variant(
    found: list[GraspCandidate],
    variant: str,
    k: int,
    template: Any,
    target: Target,
    world: CollisionWorld,
    cell: CellConfig,
    opts: PlanOptions,
) -> list[GraspCandidate]:
    """The candidates `found` for target `k` as one pass of `_plan_once` uses them (`variant`: '', 'turned',
    'leaned')."""
    if variant == "turned":
        return _turned(found, cell)
    if variant == "leaned":
        # of the grasps the jaws can open to (the evaluation's stroke test): the others need no leaning
        fits = within_stroke(np.array([c.opening_m for c in found]), cell.tool, opts.evaluation.opening_slack_m)
        return _leaned([c for c, ok in zip(found, fits, strict=True) if ok], k, template, target, world, opts)
    return found


def _leaned(
    found: list[GraspCandidate], k: int, template: Any, target: Target, world: CollisionWorld, opts: PlanOptions
) -> list[GraspCandidate]:
    """Copies of target `k`'s candidates that the cell's boxes block at the grasp, leaned, spun about the part's one
    symmetry axis or slid along the part away from them (`grasp.lean.wall_leans`). Blocked: the tool's boxes meet
    the cell's (`CollisionWorld.tool_box_hits`, the evaluation's own test) even at the grasp raised back along the
    approach by the evaluation's `max_raise_m`: a grasp whose fingertips only dip into the floor is raised by the
    evaluation, not leaned, and a leaned copy that dips its tips is kept for the evaluation to raise."""
    back = float(opts.evaluation.max_raise_m)

    def blocked(world_from_tcp: FloatArray, opening_m: FloatArray) -> FloatArray:
        raised = np.array(world_from_tcp, dtype=np.float64, copy=True)
        raised[:, :3, 3] -= raised[:, :3, 2] * back
        return world.tool_box_hits(raised, opening_m)

    axes = symmetry_axes_world(template, target.world_from_object)
    pose = target.world_from_object
    points = np.asarray(target.mesh.vertices, dtype=np.float64) @ pose[:3, :3].T + pose[:3, 3]  # type: ignore[attr-defined]
    return wall_leans(found, blocked, {k: axes[0]} if len(axes) == 1 else None, opts.leans, {k: points})


def predicted_success(plan: PickPlan, options: PlanOptions | None = None) -> float:
    """The grip mechanics' predicted success of the plan's chosen grasp with the plan's tool (`grasp.quality.judge`
    on the fitted template); 0 for a plan with no grasp, 1 with the mechanics turned off."""
    if plan.chosen is None:
        return 0.0
    mechanics = (options or PlanOptions()).evaluation.mechanics
    if mechanics is None:
        return 1.0
    c = plan.chosen.candidate
    t = plan.targets[c.target]
    mech = judge(
        c.scheme, t.mesh, t.mass_kg, t.world_from_object, c.world_from_tcp, plan.tool, mechanics, t.measured_points
    )
    return float(mech.success) if mech.ok else 0.0


def _best_tool_plan(plans: list[PickPlan], opts: PlanOptions) -> PickPlan:
    """Of one frame's plans with each tool (the cell's order), the planned one whose grasp has the best predicted
    success, then the best ranking score (the first on a tie); with none planned, the first plan carrying every
    plan's evaluations and rejection counts. Timings are summed over the tools."""
    timing: Counter[str] = Counter()
    for p in plans:
        timing.update(p.timing_ms)
    ok = [p for p in plans if p.status == "ok" and p.chosen is not None]
    if ok:
        best = max(ok, key=lambda p: (round(predicted_success(p, opts), 6), p.chosen.score if p.chosen else -np.inf))
        return replace(best, timing_ms=dict(timing))
    counts: Counter[str] = Counter()
    for p in plans:
        counts.update(p.counts)
    return replace(
        plans[0],
        evaluations=tuple(e for p in plans for e in p.evaluations),
        counts=dict(counts),
        n_feasible=sum(p.n_feasible for p in plans),
        timing_ms=dict(timing),
    )


def _candidate_options(cell: CellConfig, opts: PlanOptions) -> CandidateOptions:
    cand_opts = opts.candidates
    if cell.tool.kind == "parallel" and cand_opts.synthesis.finger_tip_m == 0.0:
        cand_opts = replace(cand_opts, synthesis=replace(cand_opts.synthesis, finger_tip_m=cell.tool.finger_depth_m))
    return cand_opts


def target_bins(cell: CellConfig, targets: Sequence[Target]) -> list[str]:
    """The name of the bin holding each target's centre (its mesh bounds' centre), '' for a target in none."""
    out = []
    for t in targets:
        lo, hi = np.asarray(t.mesh.bounds, dtype=np.float64)  # type: ignore[attr-defined]
        pose = np.asarray(t.world_from_object, dtype=np.float64)
        found = cell.bin_of(pose[:3, :3] @ ((lo + hi) / 2) + pose[:3, 3])
        out.append("" if found is None else found.name)
    return out


def _plan_bins(
    targets: list[Target],
    templates: list[Any],
    normpositions: Sequence[NormPosition],
    world: CollisionWorld,
    arm: ArmModel,
    cell: CellConfig,
    home: FloatArray,
    opts: PlanOptions,
    timing: dict[str, float],
    t_start: float,
    variant: str = "",
) -> PickPlan:
    """`plan_pick` in a cell with several bins: the bins in turn from `cell.bin` on, each with a part in it and a
    free place of its own, planned as a one-bin cell (its walls for the candidates, its rim for the entry and exit,
    its places) in the shared world; the first plan found is returned with `bin` and `bins_empty` set (a bin is
    empty when neither a target, a measured norm-position nor a surface no instance covers lies in it: a part whose
    fit was rejected, or one the segmenter missed, still fills its bin). Without one: status 'no_feasible_grasp'
    with every bin's evaluations and rejection counts."""
    assert cell.bin is not None
    names = [b.name for b in cell.bins]
    start = names.index(cell.bin.name)
    order = [cell.bins[(start + k) % len(names)] for k in range(len(names))]
    held_in = target_bins(cell, targets)
    seen = set(held_in) | {b.name for n in normpositions if (b := cell.bin_of(n.centroid)) is not None}
    seen |= {b.name for c in _uncovered_centres(world) if (b := cell.bin_of(c)) is not None}  # what was missed
    empty = tuple(b.name for b in cell.bins if b.name not in seen)
    outside = [t.name for t, b in zip(targets, held_in, strict=True) if not b]
    if outside:
        logger.info("cell %r: %d part(s) lie in no bin and are not picked: %s", cell.name, len(outside), outside)
    cand_opts = _candidate_options(cell, opts)
    evaluations: list[Evaluation] = []
    counts: Counter[str] = Counter()
    n_feasible = 0
    for b in order:
        places = cell.places_for(b)
        if b.name not in held_in or not places:
            if not places and b.name in held_in:
                logger.info("bin %r: every place its parts go to is filled", b.name)
            continue
        t0 = time.perf_counter()
        walls = b.world_from_bin[:3, :2].T.copy()
        candidates: list[GraspCandidate] = []
        for k, (target, template) in enumerate(zip(targets, templates, strict=True)):
            if held_in[k] == b.name:
                found = candidates_for_object(k, template, target.world_from_object, cell.tool.kind, cand_opts, walls)
                candidates.extend(_variant(found, variant, k, template, target, world, cell, opts))
        timing["candidates"] = timing.get("candidates", 0.0) + (time.perf_counter() - t0) * 1e3
        one = replace(cell, bin=b, places=places)
        plan = plan_from_candidates(candidates, targets, world, arm, one, home, opts, dict(timing), t_start)
        if plan.status == "ok":
            return replace(plan, bin=b.name, bins_empty=empty)
        timing.update({k: v for k, v in plan.timing_ms.items() if k != "total"})
        evaluations.extend(plan.evaluations)
        counts.update(plan.counts)
        n_feasible += plan.n_feasible
    timing["total"] = (time.perf_counter() - t_start) * 1e3
    return PickPlan(
        status="no_feasible_grasp",
        robot=cell.robot_model,
        world_from_base=cell.world_from_base,
        tool=cell.tool,
        targets=tuple(targets),
        chosen=None,
        waypoints=(),
        trajectory=None,
        evaluations=tuple(evaluations),
        counts=dict(counts),
        n_feasible=n_feasible,
        timing_ms=timing,
        cell=cell.record(),
        bins_empty=empty,
    )


def plan_from_candidates(
    candidates: list[GraspCandidate],
    targets: list[Target],
    world: CollisionWorld,
    arm: ArmModel,
    cell: CellConfig,
    home: FloatArray,
    opts: PlanOptions,
    timing: dict[str, float] | None = None,
    t_start: float | None = None,
) -> PickPlan:
    """Evaluate candidates, then build the path for the best-ranked grasp that admits one."""
    timing = {} if timing is None else timing
    t_start = time.perf_counter() if t_start is None else t_start
    t0 = time.perf_counter()
    result = evaluate_candidates(
        candidates,
        targets,
        world,
        arm,
        home,
        cell.entry_z,
        cell.lift_m,
        cell.entry_clearance_m,
        (cell.motion.workspace_min, cell.motion.workspace_max),
        opts.evaluation,
    )
    timing["evaluate"] = (time.perf_counter() - t0) * 1e3
    counts = Counter(result.counts)
    evaluations = list(result.evaluations)
    t0 = time.perf_counter()
    chosen: Evaluation | None = None
    waypoints: tuple[Waypoint, ...] = ()
    trajectory: Trajectory | None = None
    place_name = ""
    limits = SafetyLimits.from_cell(cell)  # the judge execution uses (check_plan)
    timing["timing"] = 0.0
    ranked = list(result.ranked)
    attempts = 0
    # the same grasps reached with joint 6 turned the quicker way (a half turn where the tool looks the same)
    caps = joint_caps(cell.motion.joint_velocity, cell.motion.joint_acceleration, opts.timing)
    turn_ok = half_turn_symmetric(cell.tool)
    while chosen is None:
        for ev in ranked:
            if attempts >= opts.max_plan_attempts:
                break
            attempts += 1
            path_ev = ev
            if opts.quickest_branches:
                path_ev = quickest_grasp(
                    ev, arm, cell.tool.flange_from_tcp, home, caps, turn_ok, lambda q: world.check_arm(q) is None
                )
            try:
                try:
                    waypoints, trajectory, place_name = _judged_path(
                        path_ev, targets[ev.candidate.target], world, arm, cell, home, opts, limits, timing
                    )
                except PlanningError:
                    if path_ev is ev:
                        raise
                    path_ev = ev  # no path (or none the cell allows) with joint 6 turned: the evaluation's angles
                    waypoints, trajectory, place_name = _judged_path(
                        ev, targets[ev.candidate.target], world, arm, cell, home, opts, limits, timing
                    )
            except PlanningError as exc:
                reason = getattr(exc, "reason", "path")
                logger.debug("grasp %s rejected while building the path: %s", ev.candidate.grasp_id, exc)
                counts[reason] += 1
                idx = next(i for i, e in enumerate(evaluations) if e is ev)
                evaluations[idx] = Evaluation(ev.candidate, False, reason, "", ev.world_from_tcp, ev.q, ev.branch)
                continue
            chosen = path_ev
            evaluations[next(i for i, e in enumerate(evaluations) if e is ev)] = path_ev
            break
        pending = [i for i, e in enumerate(evaluations) if e.reason == "not_evaluated"]
        if chosen is not None or attempts >= opts.max_plan_attempts or not pending:
            break
        # every grasp found so far failed while building its path: evaluate the candidates not reached yet
        t1 = time.perf_counter()
        more = evaluate_candidates(
            [candidates[i] for i in pending],
            targets,
            world,
            arm,
            home,
            cell.entry_z,
            cell.lift_m,
            cell.entry_clearance_m,
            (cell.motion.workspace_min, cell.motion.workspace_max),
            replace(opts.evaluation, max_feasible=0, max_feasible_per_target=0),
        )
        timing["evaluate"] += (time.perf_counter() - t1) * 1e3
        counts["not_evaluated"] -= len(pending)
        for i, ev in zip(pending, more.evaluations, strict=True):
            evaluations[i] = ev
            if not ev.feasible:
                counts[ev.reason] += 1
        ranked = list(more.ranked)
        if not ranked:
            break
    if counts.get("not_evaluated", 1) == 0:
        del counts["not_evaluated"]
    timing["path"] = (time.perf_counter() - t0) * 1e3 - timing["timing"]
    if chosen is None:
        trajectory = None
    timing["total"] = (time.perf_counter() - t_start) * 1e3
    n_feasible = sum(1 for e in evaluations if e.feasible)
    return PickPlan(
        status="ok" if chosen is not None else "no_feasible_grasp",
        robot=cell.robot_model,
        world_from_base=cell.world_from_base,
        tool=cell.tool,
        targets=tuple(targets),
        chosen=chosen,
        waypoints=waypoints,
        trajectory=trajectory,
        evaluations=tuple(evaluations),
        counts=dict(counts),
        n_feasible=n_feasible,
        timing_ms=timing,
        place=place_name,
        cell=cell.record(),
    )


def _judged_path(
    ev: Evaluation,
    target: Target,
    world: CollisionWorld,
    arm: ArmModel,
    cell: CellConfig,
    home: FloatArray,
    opts: PlanOptions,
    limits: SafetyLimits,
    timing: dict[str, float],
) -> tuple[tuple[Waypoint, ...], Trajectory, str]:
    """`_build_path`, timed and judged by `_timed_for_stream` (its ms added to timing['timing']): the cell judges
    it as execution judges plan.json (`limits.check_path` on the waypoints and the samples as plan.json rounds
    them) and the driver's check passes its servo stream (re-timed with a softer jerk cap where it does not); a
    plan the cell refuses raises _PathRejected with reason 'path_cell_<check>', one whose stream no timing down to
    the floor passes 'path_stream_<check>'."""
    waypoints, pieces, place_name = _build_path(ev, target, world, arm, cell, home, opts, limits)
    trajectory = _timed_for_stream(pieces, waypoints, arm, cell, opts.timing, limits, timing)
    return waypoints, trajectory, place_name


def _carried(trajectory: Trajectory) -> tuple[FloatArray, FloatArray]:
    """The samples as plan.json carries them (PickPlan.to_json rounds t to 1 us and q to 1e-9 rad): what execution
    judges and streams (Python's round on the samples as floats, as to_json does; tolist instead of a float() per
    element)."""
    t = np.array([round(v, 6) for v in np.asarray(trajectory.t, dtype=np.float64).tolist()])
    q_rows = np.asarray(trajectory.q, dtype=np.float64)
    q = np.array([round(v, 9) for v in q_rows.ravel().tolist()]).reshape(q_rows.shape)
    return t, q


STREAM_CUTS = ("grasp", "place")
"""The waypoints where execution ends one streamed piece and starts the next (the arm rests there while the gripper
acts): `execution.plan.ExecuteOptions`' close_at and open_at."""


def _timed_for_stream(
    pieces: list[PathPiece],
    waypoints: Sequence[Waypoint],
    arm: ArmModel,
    cell: CellConfig,
    options: TimingOptions,
    limits: SafetyLimits,
    timing: dict[str, float],
) -> Trajectory:
    """The plan's trajectory (`_time_pieces`), judged by the cell as execution judges plan.json and streamable as
    the driver streams it; its ms (timing and stream check) added to timing['timing'].

    The samples as plan.json rounds them pass `limits.check_path` with the waypoints (else _PathRejected
    'path_cell_<check>'). Then the servo commands: execution streams the trajectory in pieces cut where the gripper
    acts (STREAM_CUTS), each as a cubic spline through its samples every options.stream_period_s, and the driver
    refuses a whole piece whose commands exceed a cap (`GuardedDriver.follow_trajectory`); `cell.stream
    .check_stream` runs that same check here. The spline overshoots the sampled profile at sharp acceleration
    corners, the more the higher the jerk cap: at the default 100 rad/s^3 the commands of 30 unseen bins peaked at
    0.9994 of the acceleration cap, so some unseen path will exceed it, and the driver would refuse that plan at
    run time (nothing moves, but the pick is lost). A plan whose stream exceeds is re-timed with the jerk cap
    halved (softer corners, less overshoot; only that plan pays the slower motion) down to
    options.stream_jerk_floor_rad_s3; a stream still refused there (or a trapezoid timing, which no jerk cap
    changes) is a rejected grasp, reason 'path_stream_<check>', and the next one is tried."""
    names = [w.name for w in waypoints]
    wq = np.stack([w.q for w in waypoints])
    opts = options
    while True:
        t0 = time.perf_counter()
        trajectory = _time_pieces(pieces, arm, cell, opts)
        timing["timing"] += (time.perf_counter() - t0) * 1e3
        t, q = _carried(trajectory)
        try:
            limits.check_path(names, wq, t, q)
        except SafetyViolation as exc:
            raise _PathRejected(f"the cell refuses the plan: {exc}", _cell_reason("path", exc)) from exc
        t0 = time.perf_counter()
        try:
            check_stream(t, q, stream_cuts(q, names, wq, STREAM_CUTS), limits, opts.stream_period_s)
            return trajectory
        except SafetyViolation as exc:
            halved = 0.5 * opts.jerk_rad_s3
            if opts.method != "ruckig" or halved < opts.stream_jerk_floor_rad_s3 * (1.0 - 1e-9):
                check = exc.detail.get("check", "input") if isinstance(exc.detail, dict) else "input"
                raise _PathRejected(
                    f"the driver would refuse the plan's servo stream at jerk cap {opts.jerk_rad_s3:g} rad/s^3 "
                    f"(re-timed down to the floor {opts.stream_jerk_floor_rad_s3:g}): {exc}",
                    f"path_stream_{check}",
                ) from exc
            logger.debug("servo stream refused at jerk %g rad/s^3 (%s): re-timed at %g", opts.jerk_rad_s3, exc, halved)
            opts = replace(opts, jerk_rad_s3=halved)
        finally:
            timing["timing"] += (time.perf_counter() - t0) * 1e3


def _cell_reason(stage: str, exc: SafetyViolation) -> str:
    """Rejection reason for a plan the cell's judge refused: '<stage>_cell_<check>' (check: the limit it broke)."""
    check = exc.detail.get("check", "input") if isinstance(exc.detail, dict) else "input"
    return f"{stage}_cell_{check}"


def _time_pieces(pieces: list[PathPiece], arm: ArmModel, cell: CellConfig, options: TimingOptions) -> Trajectory:
    """The plan's trajectory: Ruckig through the pieces (options.method 'ruckig'), or rest-to-rest trapezoids per
    piece ('trapezoid', and where Ruckig's samples fail the planner's cap check)."""
    motion = cell.motion
    vmax = np.asarray(motion.joint_velocity, dtype=np.float64)
    amax = np.asarray(motion.joint_acceleration, dtype=np.float64)
    if options.method == "ruckig":
        try:
            tcp_accel = float(motion.tcp_acceleration_m_s2)
            return time_path(pieces, vmax, amax, arm.lower, arm.upper, motion.tcp_speed_m_s, tcp_accel, options)
        except PlanningError as exc:
            logger.warning("Ruckig timing failed (%s); timing the path with rest-to-rest trapezoids", exc)
    return time_parameterise(
        [p.points for p in pieces], vmax, amax, [p.tcp for p in pieces], motion.tcp_speed_m_s, options
    )


class _ConfigFree:
    """Collision-free test of one configuration (the world as it stands, tool at `opening` m) for the joint-space
    planner, with the vectorised sphere pre-test `clear_batch` for dense edge checks."""

    def __init__(self, world: CollisionWorld, opening: float) -> None:
        self.world = world
        self.opening = opening

    def __call__(self, q: FloatArray) -> bool:
        return self.world.check_config(q, self.opening) is None

    def clear_batch(self, qs: FloatArray) -> BoolArray:
        return self.world.configs_clear(qs, self.opening)


class _PathRejected(PlanningError):
    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


def _line(
    arm: ArmModel,
    tcp_from_flange: FloatArray,
    a: FloatArray,
    b: FloatArray,
    q_start: FloatArray,
    branch: int,
    opts: PlanOptions,
) -> tuple[FloatArray, FloatArray]:
    """Joint samples (K, 6) and TCP positions (K, 3) of the straight TCP line a -> b (same orientation)."""
    return _lines(arm, tcp_from_flange, np.stack([a, b]), q_start, branch, opts)[0]


def _lines(
    arm: ArmModel,
    tcp_from_flange: FloatArray,
    corners: FloatArray,
    q_start: FloatArray,
    branch: int,
    opts: PlanOptions,
) -> list[tuple[FloatArray, FloatArray]]:
    """`_line` through the TCP poses `corners` (L + 1, 4, 4) one after the other (each line starts where the one
    before ends), IK solved for all their samples at once; the first line that fails raises."""
    pieces = []
    for a, b in zip(corners[:-1], corners[1:], strict=True):
        dist = float(np.linalg.norm(b[:3, 3] - a[:3, 3]))
        n = max(int(np.ceil(dist / opts.cartesian_step_m)), 1)
        s = np.linspace(0.0, 1.0, n + 1)
        poses = np.repeat(a[None], n + 1, axis=0)
        poses[:, :3, 3] = a[:3, 3] + s[:, None] * (b[:3, 3] - a[:3, 3])
        pieces.append(poses)
    q_all, exists_all, _ = arm.ik_reasons(np.concatenate(pieces) @ tcp_from_flange)
    out = []
    start = 0
    prev = q_start
    two_pi = 2 * np.pi
    for poses in pieces:
        q, exists = q_all[start : start + len(poses)], exists_all[start : start + len(poses)]
        start += len(poses)
        if not exists[:, branch].all():
            raise _PathRejected("straight line leaves the IK branch", "path_ik")
        raw = q[:, branch]
        # each sample by whole turns next to the one before (the first next to prev): the turns add up along the line
        turns = np.cumsum(np.round((np.vstack([prev, raw[:-1]]) - raw) / two_pi), axis=0)
        qs = raw + two_pi * turns
        if np.abs(np.diff(np.vstack([prev, qs]), axis=0)).max() > opts.max_joint_jump_rad:
            raise _PathRejected("straight line passes a singularity (joint jump)", "path_singularity")
        if np.any(qs < arm.lower - 1e-9) or np.any(qs > arm.upper + 1e-9):
            raise _PathRejected("straight line leaves the joint limits", "path_joint_limits")
        out.append((qs, poses[:, :3, 3]))
        prev = qs[-1]
    return out


def _place_pose(place: PlaceSpec, tcp_from_object: FloatArray, target: Target, drop_m: float) -> FloatArray:
    """TCP pose at release: the place orientation, raised so the held object's lowest point is `drop_m` above the
    place height. With `place.align_part` the TCP first turns about the world z axis so the object's x axis (held
    as fitted: `tcp_from_object`) points along the place pose's x axis in the horizontal plane (a part whose x axis
    stands vertical keeps the place orientation)."""
    pose = place.world_from_tcp.copy()
    if place.align_part:
        a = (pose @ tcp_from_object)[:3, 0]
        b = place.world_from_tcp[:3, 0]
        if np.hypot(a[0], a[1]) > 1e-6 and np.hypot(b[0], b[1]) > 1e-6:
            yaw = np.arctan2(b[1], b[0]) - np.arctan2(a[1], a[0])
            c, s = np.cos(yaw), np.sin(yaw)
            pose[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ pose[:3, :3]
    verts = np.asarray(target.mesh.vertices, dtype=np.float64)  # type: ignore[attr-defined]
    obj = pose @ tcp_from_object
    lowest = float((verts @ obj[:3, :3].T)[:, 2].min() + obj[2, 3])
    pose[2, 3] += (place.world_from_tcp[2, 3] - lowest) + drop_m
    return pose


def _place_motion(
    place: PlaceSpec,
    target: Target,
    tcp_from_object: FloatArray,
    q_from: FloatArray,
    world: CollisionWorld,
    arm: ArmModel,
    tcp_from_flange: FloatArray,
    free_held: _ConfigFree,
    opts: PlanOptions,
    caps: tuple[FloatArray, FloatArray, FloatArray],
    turn_ok: bool,
    limits: SafetyLimits,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, PlaceSpec]:
    """Straight pre-place -> place (held) and place -> post-place (released) lines through the place pose, or an
    equivalent one (`branches.place_poses`, with opts.quickest_branches; `turn_ok`: the tool looks the same turned
    half a turn), on the branch with the quickest estimated motion from `q_from` (caps: `timing.joint_caps`) that
    admits them and whose waypoints and straight joint segments from `q_from` the cell's judge (`limits`) allows."""
    place_pose = _place_pose(place, tcp_from_object, target, opts.place_drop_m)
    verts = np.asarray(target.mesh.vertices, dtype=np.float64)  # type: ignore[attr-defined]
    poses = [place_pose]
    if opts.quickest_branches:
        poses = place_poses(place_pose, tcp_from_object, verts, turn_ok and not place.align_part)
    options = ranked_place_configs(
        poses, place.approach_m, q_from, arm, tcp_from_flange, caps if opts.quickest_branches else None
    )
    if not options:
        raise _PathRejected(f"place {place.name!r}: pre-place pose out of reach", "place_ik")
    last = _PathRejected(f"place {place.name!r}: no branch", "place_ik")
    for place_pose, pre_place, q_pp, pb in options:
        try:
            (seg_place, tcp_place), (seg_post, tcp_post) = _lines(
                arm, tcp_from_flange, np.stack([pre_place, place_pose, pre_place]), q_pp, pb, opts
            )
        except _PathRejected as exc:
            last = exc
            continue
        try:  # execution judges the straight joint segments retreat -> pre_place -> place -> post_place
            limits.check_path(
                ("retreat", "pre_place", "place", "post_place"),
                np.stack([q_from, seg_place[0], seg_place[-1], seg_post[-1]]),
            )
        except SafetyViolation as exc:
            last = _PathRejected(
                f"place {place.name!r}: the cell refuses this branch: {exc}", _cell_reason("place", exc)
            )
            continue
        placing = seg_place[:-1][~world.configs_clear(seg_place[:-1], free_held.opening)]
        if not all(free_held(q) for q in placing):
            last = _PathRejected(f"place {place.name!r}: collision placing", "place_collision")
            continue
        with world.empty_handed():  # the arm alone where the spheres cannot prove the configuration clear
            leaving = seg_post[1:][~world.configs_clear(seg_post[1:], free_held.opening)]
            leaving_hit = any(world.check_arm(q) is not None for q in leaving)
        if leaving_hit:
            last = _PathRejected(f"place {place.name!r}: collision leaving", "place_collision")
            continue
        return seg_place, tcp_place, seg_post, tcp_post, place
    raise last


def _build_path(
    ev: Evaluation,
    target: Target,
    world: CollisionWorld,
    arm: ArmModel,
    cell: CellConfig,
    home: FloatArray,
    opts: PlanOptions,
    limits: SafetyLimits,
) -> tuple[tuple[Waypoint, ...], list[PathPiece], str]:
    """Waypoints and the pieces of the path (lines, and joint edges with the collision test a blend through their
    ends must pass) of one evaluated grasp, and the place used; _PathRejected when some part has no path."""
    if ev.q is None or ev.world_from_tcp is None:
        raise _PathRejected("evaluation carries no configurations", "path")
    tool = cell.tool
    c = ev.candidate
    tcp_from_flange = invert_pose(tool.flange_from_tcp)
    poses, qs, b = ev.world_from_tcp, ev.q, ev.branch
    tcp_from_object = invert_pose(poses[2]) @ target.world_from_object
    opening = c.opening_m

    free_empty = _ConfigFree(world, opening)
    free_held = free_empty  # the world's held object (attached or not) is part of every check

    # 1. straight lines first (cheap), transfers (joint-space search) last
    (seg_entry, tcp_entry), (seg_pre, tcp_pre), (seg_lift, tcp_lift), (seg_exit, tcp_exit) = _lines(
        arm, tcp_from_flange, poses, qs[0], b, opts
    )
    clear = world.configs_clear(seg_entry[1:], opening)
    for q in seg_entry[1:][~clear]:
        if not free_empty(q):
            raise _PathRejected("collision on the way into the bin", "path_collision")
    backoff = opts.evaluation.contact_backoff_m + opts.cartesian_step_m
    # samples the bounding spheres prove clear in the whole world pass both tests below without fcl; those within
    # the backoff of the grasp (the tool at the target) are always checked, so the last check stays at the grasp
    far = np.linalg.norm(tcp_pre[1:-1] - tcp_pre[-1], axis=1) > backoff
    pre_clear = np.zeros(len(far), dtype=bool)
    if far.any():
        pre_clear[far] = world.configs_clear(seg_pre[1:-1][far], opening)
    for q, p, ok in zip(seg_pre[1:-1], tcp_pre[1:-1], pre_clear, strict=True):
        if ok:
            continue
        if np.linalg.norm(p - tcp_pre[-1]) <= backoff:
            # the tool touches the target by design at the end: everything else is still checked
            with world.without(target.name):
                hit = world.check_config(q, opening)
            if hit is not None or world.check_arm(q) is not None:
                raise _PathRejected("collision at the end of the approach", "path_collision")
            continue
        if not free_empty(q):
            raise _PathRejected("collision on the approach", "path_collision")
    with world.holding(target.name, target.mesh, tcp_from_object):  # type: ignore[arg-type]
        lifted = tcp_lift - tcp_lift[0]
        out_qs = np.concatenate([seg_lift[1:], seg_exit[1:]])
        out_clear = world.configs_clear(out_qs, opening)
        for q, dz, ok in zip(
            out_qs,
            list(np.linalg.norm(lifted[1:], axis=1)) + [np.inf] * (len(seg_exit) - 1),
            out_clear,
            strict=True,
        ):
            if ok:
                continue
            # the first millimetres may graze neighbours the fit left touching (pose noise): tool and arm only
            skip_held = ("object", "clutter") if dz < opts.release_tolerance_m else ()
            if world.check_config(q, opening, skip_held=skip_held) is not None:
                raise _PathRejected("collision while lifting the object out", "path_collision")
        place_err: _PathRejected | None = None
        found = None
        for place in cell.places:
            try:
                found = _place_motion(
                    place, target, tcp_from_object, seg_exit[-1], world, arm, tcp_from_flange, free_held, opts,
                    joint_caps(cell.motion.joint_velocity, cell.motion.joint_acceleration, opts.timing),
                    half_turn_symmetric(tool), limits,
                )  # fmt: skip
                place_err = None
                break
            except _PathRejected as exc:
                place_err = exc
        if found is None:
            raise place_err or _PathRejected("no place pose given", "place_ik")
        seg_place, tcp_place, seg_post, tcp_post, place = found
        # 2. transfers: exit -> pre-place holding the object, then home -> entry empty-handed
        try:
            transfer_out = plan_joint_motion(seg_exit[-1], seg_place[0], free_held, arm.lower, arm.upper, opts.motion)
        except PlanningError as exc:
            raise _PathRejected(f"no joint path from the bin exit to the place: {exc}", "place_transfer") from exc
    try:
        transfer_in = plan_joint_motion(home, seg_entry[0], free_empty, arm.lower, arm.upper, opts.motion)
    except PlanningError as exc:
        raise _PathRejected(f"no joint path from home to the bin entry: {exc}", "path_transfer") from exc
    fk = arm.fk
    flange_from_tcp = tool.flange_from_tcp

    def wp(name: str, q: FloatArray) -> Waypoint:
        return Waypoint(name, np.asarray(q, dtype=np.float64), fk(q) @ flange_from_tcp)

    waypoints = (
        wp("home", home),
        wp("entry", seg_entry[0]),
        wp("pre_grasp", seg_pre[0]),
        wp("grasp", seg_pre[-1]),
        wp("lift", seg_lift[-1]),
        wp("retreat", seg_exit[-1]),
        wp("pre_place", seg_place[0]),
        wp("place", seg_place[-1]),
        wp("post_place", seg_post[-1]),
    )

    box_lo, box_hi = cell.motion.workspace_min, cell.motion.workspace_max

    def clear_empty(qs: FloatArray) -> bool:  # a blended transfer into the bin, empty-handed
        tcp = (fk(qs) @ flange_from_tcp)[:, :3, 3]  # execution refuses a TCP outside the workspace box
        if np.any(tcp < box_lo) or np.any(tcp > box_hi):
            return False
        return all(free_empty(q) for q in qs[~world.configs_clear(qs, opening)])

    def clear_held(qs: FloatArray) -> bool:  # a blended transfer to the place, holding the object
        with world.holding(target.name, target.mesh, tcp_from_object):  # type: ignore[arg-type]
            return clear_empty(qs)

    # stops: at the grasp and the place (the gripper acts) and at the end; pre_grasp and the other waypoints are
    # passed at speed where the path allows (time_path)
    pieces = [
        PathPiece(np.stack(transfer_in[k : k + 2]), None, False, clear_empty) for k in range(len(transfer_in) - 1)
    ]
    pieces += [PathPiece(seg_entry, tcp_entry), PathPiece(seg_pre, tcp_pre, rest_after=True)]
    pieces += [PathPiece(seg_lift, tcp_lift), PathPiece(seg_exit, tcp_exit)]
    pieces += [
        PathPiece(np.stack(transfer_out[k : k + 2]), None, False, clear_held) for k in range(len(transfer_out) - 1)
    ]
    pieces += [PathPiece(seg_place, tcp_place, rest_after=True), PathPiece(seg_post, tcp_post, rest_after=True)]
    return waypoints, pieces, place.name


#: how far a rejected candidate got, cheapest test first: the closest call is the one rejected latest
_STAGE_ORDER = (
    "not_evaluated",
    "approach_angle",
    "stroke",
    "payload",
    "workspace",
    "collision_cell",
    "ik",
    "joint_limits",
    "collision",
    "friction_cone",
    "pad_contact",
    "slip_torque",
    "seal",
    "suction_load",
    "suction_torque",
    "path",
    "place",
)


def _stage_rank(reason: str) -> int:
    if reason in _STAGE_ORDER:
        return _STAGE_ORDER.index(reason)
    for k in range(len(_STAGE_ORDER) - 1, -1, -1):
        if reason.startswith(_STAGE_ORDER[k] + "_"):
            return k
    return 0


@dataclass(frozen=True)
class TargetRejections:
    """Why one perceived object got no grasp: its target name and template, rejection counts by reason, and the
    closest call (the rejected candidate that passed the most tests; ties by its quality): id, scheme, reason, the
    pose it failed at, and its world_from_tcp (4, 4)."""

    target: str
    template: str
    counts: dict[str, int]
    best_id: str
    best_scheme: str
    best_reason: str
    best_pose: str
    best_world_from_tcp: FloatArray
    best_opening_m: float

    def to_json(self) -> dict[str, Any]:
        return {
            "target": self.target,
            "template": self.template,
            "rejected_by_reason": dict(sorted(self.counts.items())),
            "best_rejected": {
                "id": self.best_id,
                "scheme": self.best_scheme,
                "reason": self.best_reason,
                "pose": self.best_pose,
                "world_from_tcp": np.asarray(self.best_world_from_tcp).tolist(),
                "opening_m": self.best_opening_m,
            },
        }


def rejections_by_target(plan: PickPlan) -> list[TargetRejections]:
    """Per target of `plan` (in target order; targets without candidates left out): counts and the closest call."""
    per: dict[int, list[Evaluation]] = {}
    for ev in plan.evaluations:
        if not ev.feasible:
            per.setdefault(ev.candidate.target, []).append(ev)
    out = []
    for k, evs in sorted(per.items()):
        best = max(evs, key=lambda e: (_stage_rank(e.reason), e.candidate.quality))
        target = plan.targets[k]
        out.append(
            TargetRejections(
                target.name,
                target.template,
                dict(Counter(e.reason for e in evs)),
                best.candidate.grasp_id,
                best.candidate.scheme,
                best.reason,
                best.pose,
                np.asarray(best.candidate.world_from_tcp, dtype=np.float64),
                float(best.candidate.opening_m),
            )
        )
    return out


def stop_line(plan: PickPlan, max_reasons: int = 3) -> str:
    """One line saying why `plan` found no grasp: the parts left and, for each, its commonest rejection reasons
    and the closest call."""
    rows = rejections_by_target(plan)
    if not plan.targets:
        if plan.uncovered_voxels:
            return (
                "no feasible grasp: no accepted template fit to pick, but surfaces no instance covers remain in the "
                f"bin ({plan.uncovered_voxels} clutter voxels): parts the segmenter did not find?"
            )
        return "no feasible grasp: no accepted template fit to pick (nothing perceived as a known part)"
    parts = []
    for r in rows:
        top = sorted(r.counts.items(), key=lambda kv: (-kv[1], kv[0]))[:max_reasons]
        reasons = ", ".join(f"{k} {v}" for k, v in top)
        closest = f"closest {r.best_id} ({r.best_reason}" + (f" at {r.best_pose})" if r.best_pose else ")")
        parts.append(f"{r.template or r.target}: {reasons}; {closest}")
    names = ", ".join(t.template or t.name for t in plan.targets)
    return f"no feasible grasp for {len(plan.targets)} part(s) left ({names}): " + " | ".join(parts)
