"""Five-pose candidate evaluation: bin entry, pre-grasp, grasp, post-grasp lift, bin exit.

Cheap vectorised tests run on every candidate first (approach angle, stroke, payload, workspace, the tool's boxes
against the cell's boxes); then, one candidate at a time, best prior first, until enough feasible grasps are found:
the tool's fcl checks (about 0.3 ms; they stop nine in ten of the candidates that get here, on a neighbour), IK at
all five poses over all analytic branches, the arm's fcl checks per branch, and last the grip mechanics (about 1 ms,
and they rarely reject a collision-free grasp; their predicted success only lowers a prior, so the unjudged prior is
an upper bound and the order stays exact). Every rejected candidate keeps its reason: 'approach_angle', 'stroke',
'workspace', 'ik', 'joint_limits', 'collision_<what>' (cell, object, clutter, self), 'payload', the grip mechanics'
reasons ('friction_cone', 'pad_contact', 'slip_torque', 'seal', 'suction_load', 'suction_torque', `grasp.quality`);
candidates never reached are counted as 'not_evaluated'.
"""

from __future__ import annotations

import heapq
import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.grasp.quality import QualityOptions, judge
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.plan import Evaluation, Target
from normpos_grasp.records.tool import ToolModel
from normpos_grasp.typing import BoolArray, FloatArray, IntArray

if TYPE_CHECKING:
    from normpos_grasp.collision.world import CollisionWorld, Hit

logger = logging.getLogger(__name__)

POSE_NAMES = ("entry", "pre_grasp", "grasp", "lift", "exit")


@dataclass(frozen=True)
class EvaluationOptions:
    """Settings of candidate evaluation.

    max_approach_up: largest world-z component of the approach direction (0: horizontal; approaches from below
    the object are rejected as 'approach_angle'). contact_backoff_m: the tool is checked at the grasp pose moved
    back by this much along the approach (suction cups and jaw faces touch the target by design), m.
    max_feasible / max_feasible_per_target: stop the collision stage after this many feasible grasps (0: check all).
    clearance: also test the tool grown by the world's clearance (feeds the ranking).
    noise_margin: check the tool at the grasp against the other objects and clutter grown by the world's noise margin
    (`CollisionWorld.set_tool(noise_margin_m=...)`, 2 mm: fitted poses are off by about that under D435 noise).
    tip_margin_m: the tool at the grasp must also clear the cell's boxes when pushed this much further along the
    approach (fitted poses are off by millimetres: fingertips keep this margin above the bin floor), m.
    max_raise_m / raise_step_m: a parallel grasp whose fingers hit the cell (floor) at the grasp is raised back
    along the approach in these steps up to this far, m, as long as the jaw tips still reach `min_contact_m` (or
    `min_contact_share` of the part's depth along its box axis nearest the approach, if less: 3.2 mm of an 8 mm
    plate) past the part's approached face (m); the pad contact itself is judged by `grasp.quality`; the raised grasp
    replaces the candidate. opening_slack_m: a parallel grasp
    whose opening (part width + synthesis clearance) exceeds the stroke by at most this much is opened to the full
    stroke instead (less clearance beside the part; the collision checks still decide), m. Weights of the ranking
    score: quality, approach (vertical approach preferred), travel (joint distance from home, per rad),
    priority (template priority), clearance, height (higher objects first, per m). mechanics: grip mechanics
    (`grasp.quality`): candidates it predicts to slip, turn or lose the seal are rejected with its reason, and its
    predicted success scales the geometric quality in the ranking (None: the geometric quality alone, no check).
    """

    max_approach_up: float = 0.2
    contact_backoff_m: float = 0.003
    max_feasible: int = 5
    max_feasible_per_target: int = 2
    clearance: bool = True
    w_quality: float = 1.0
    w_approach: float = 0.5
    w_travel: float = 0.05
    w_priority: float = 0.5
    w_clearance: float = 0.3
    w_height: float = 2.0
    noise_margin: bool = True
    tip_margin_m: float = 0.003
    max_raise_m: float = 0.016
    raise_step_m: float = 0.001
    min_contact_m: float = 0.005
    min_contact_share: float = 0.4
    opening_slack_m: float = 0.012
    mechanics: QualityOptions | None = QualityOptions()


@dataclass(frozen=True, eq=False)
class EvaluationResult:
    """All verdicts, ranked feasible ones first (best first)."""

    evaluations: tuple[Evaluation, ...]
    ranked: tuple[Evaluation, ...]
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def n_feasible(self) -> int:
        return len(self.ranked)


def within_stroke(openings: FloatArray, tool: ToolModel, slack_m: float = 0.0) -> BoolArray:
    """(N,) whether a parallel tool's jaws take the openings (N,) m: from tool.min_opening_m to tool.stroke_m +
    slack_m (the evaluation sets openings within `EvaluationOptions.opening_slack_m` above the stroke to the
    stroke), 1 nm tolerance at both ends."""
    o = np.asarray(openings, dtype=np.float64)
    return ~((o > tool.stroke_m + slack_m + 1e-9) | (o < tool.min_opening_m - 1e-9))


def five_poses(c: GraspCandidate, entry_z: float, lift_m: float, below_tcp_m: float) -> FloatArray:
    """(5, 4, 4) world_from_tcp at entry, pre-grasp, grasp, lift and exit for candidate `c`.

    Pre-grasp backs off `approach_m` along the approach axis; lift rises `lift_m` in world z; entry and exit are the
    pre-grasp and lift poses raised to `entry_z` (the rim + the cell's entry clearance, m), the exit also by
    `below_tcp_m`, the held object's depth below the TCP (m): the held object's lowest point leaves the bin at the
    same clearance above the rim as the empty tool's TCP enters it."""
    g = c.world_from_tcp
    a = g[:3, 2]
    pre = g.copy()
    pre[:3, 3] -= a * c.approach_m
    lift = g.copy()
    lift[2, 3] += lift_m
    entry = pre.copy()
    entry[2, 3] = max(pre[2, 3], entry_z)
    exit_ = lift.copy()
    exit_[2, 3] = max(lift[2, 3], entry_z + below_tcp_m if np.isfinite(entry_z) else lift[2, 3])
    return np.stack([entry, pre, g, lift, exit_])


def five_poses_batch(
    g: FloatArray, approach_m: FloatArray, entry_z: float, lift_m: float, below_tcp_m: FloatArray
) -> FloatArray:
    """(N, 5, 4, 4) five poses for grasp poses g (N, 4, 4); vectorised `five_poses`."""
    n = len(g)
    out = np.repeat(g[:, None], 5, axis=1)
    out[:, 1, :3, 3] -= g[:, :3, 2] * approach_m[:, None]
    out[:, 3, 2, 3] += lift_m
    if np.isfinite(entry_z):
        out[:, 0, :3, 3] = out[:, 1, :3, 3]
        out[:, 0, 2, 3] = np.maximum(out[:, 1, 2, 3], entry_z)
        out[:, 4, :3, 3] = out[:, 3, :3, 3]
        out[:, 4, 2, 3] = np.maximum(out[:, 3, 2, 3], entry_z + below_tcp_m)
    else:
        out[:, 0] = out[:, 1]
        out[:, 4] = out[:, 3]
    del n
    return out


def evaluate_candidates(
    candidates: list[GraspCandidate],
    targets: list[Target],
    world: CollisionWorld,
    arm: ArmModel,
    home_q: FloatArray,
    entry_z: float,
    lift_m: float,
    entry_clearance_m: float,
    workspace: tuple[FloatArray, FloatArray],
    options: EvaluationOptions | None = None,
) -> EvaluationResult:
    """Evaluate `candidates` (for objects `targets`, each also a world element of the same name) at five poses.

    entry_z: the bin entry height, m: the rim + `entry_clearance_m` (the cell's `entry_z`), so the held part leaves
    the bin with its lowest point `entry_clearance_m` above the rim, as the empty tool enters (`five_poses`)."""
    del entry_clearance_m  # held in entry_z; the exit adds only the held part's depth below the TCP
    opts = options or EvaluationOptions()
    tool = world.tool
    if tool is None:
        raise ValueError("world has no tool: call world.set_tool first")
    candidates = list(candidates)
    n = len(candidates)
    verdict: list[Evaluation | None] = [None] * n
    if n == 0:
        return EvaluationResult((), (), {})
    flange_from_tcp = tool.flange_from_tcp
    tcp_from_flange = invert_pose(flange_from_tcp)
    g = np.stack([c.world_from_tcp for c in candidates])
    approach = g[:, :3, 2]
    openings = np.array([c.opening_m for c in candidates])
    lowest = np.array(
        [
            float(
                (np.asarray(t.mesh.vertices, dtype=np.float64) @ t.world_from_object[2, :3]).min()  # type: ignore[attr-defined]
                + t.world_from_object[2, 3]
            )
            for t in targets
        ]
    )
    target_idx = np.array([c.target for c in candidates])
    below = np.maximum(g[:, 2, 3] - lowest[target_idx], 0.0)
    poses = five_poses_batch(g, np.array([c.approach_m for c in candidates]), entry_z, lift_m, below)

    def reject(i: int, reason: str, pose: str = "") -> None:
        verdict[i] = Evaluation.rejected(candidates[i], reason, pose, poses[i])

    # 1. vectorised screens
    if tool.kind == "parallel" and opts.opening_slack_m > 0:
        narrow = (openings > tool.stroke_m + 1e-9) & (openings <= tool.stroke_m + opts.opening_slack_m)
        for j in np.flatnonzero(narrow):
            candidates[int(j)] = replace(candidates[int(j)], opening_m=float(tool.stroke_m))
            openings[int(j)] = tool.stroke_m
    for j in np.flatnonzero(approach[:, 2] > opts.max_approach_up):
        reject(int(j), "approach_angle", "grasp")
    if tool.kind == "parallel":
        for j in np.flatnonzero(~within_stroke(openings, tool)):
            if verdict[int(j)] is None:
                reject(int(j), "stroke", "grasp")
    for i, c in enumerate(candidates):
        if verdict[i] is None and targets[c.target].mass_kg > tool.payload_kg:
            reject(i, "payload", "grasp")
    lo, hi = workspace
    pos = poses[:, :, :3, 3]
    out_ws = np.any((pos < lo) | (pos > hi), axis=(1, 2))
    for j in np.flatnonzero(out_ws):
        if verdict[int(j)] is None:
            reject(int(j), "workspace", POSE_NAMES[int(np.argmax(np.any((pos[j] < lo) | (pos[j] > hi), axis=1)))])
    # tool boxes against the static cell boxes at grasp, pre-grasp and entry: exact, vectorised
    alive = np.array([v is None for v in verdict])
    idx = np.flatnonzero(alive)
    if len(idx):
        # grasp depth adapted to the clearance below the part: fingertips stop tip_margin_m above the cell boxes
        raised = _raise_grasps(idx, g, approach, openings, target_idx, targets, world, tool, opts)
        for jr, new_g in raised.items():
            c = candidates[jr]
            candidates[jr] = replace(c, grasp_id=f"{c.grasp_id}@up", world_from_tcp=new_g)
        if raised:
            rows = np.array(sorted(raised))
            g[rows] = np.stack([raised[int(j)] for j in rows])
            poses[rows] = five_poses_batch(
                g[rows],
                np.array([candidates[int(j)].approach_m for j in rows]),
                entry_z,
                lift_m,
                np.maximum(g[rows, 2, 3] - lowest[target_idx[rows]], 0.0),
            )
        for p_idx in (2, 1, 0):
            hits = world.tool_box_hits(poses[idx, p_idx], openings[idx])
            for j in idx[hits]:
                reject(int(j), "collision_cell", POSE_NAMES[p_idx])
            idx = idx[np.logical_not(hits)]
    # 2. prior order: object height, grasp quality, approach angle, priority. The grip mechanics scale the quality by
    # their predicted success (<= 1), so the unjudged quality is an upper bound of each prior: candidates are taken
    # best bound first and judged only when they are reached (the judge costs about a millisecond)
    success = np.array([c.quality for c in candidates])
    heights = np.array([targets[c.target].height_m for c in candidates])
    priorities = np.array([c.priority for c in candidates])
    prior = (
        opts.w_height * heights
        + opts.w_quality * success
        + opts.w_approach * (-approach[:, 2])
        + opts.w_priority * priorities
    )
    order = [int(i) for i in np.argsort(-prior, kind="stable") if verdict[int(i)] is None]

    # 3. best prior first: the tool's fcl checks at grasp, pre-grasp and entry (most candidates stop here: the tool
    # meets a neighbour), IK at all five poses on all branches, the arm's checks per branch, then the mechanics; a
    # candidate whose judged prior falls below its bound goes back in line at its exact prior (every prior left is
    # at most its bound, so candidates leave in exact prior order, ties by index). Candidates never reached are
    # 'not_evaluated'.
    feasible: list[Evaluation] = []
    per_target: Counter[int] = Counter()
    heap = [(-float(prior[i]), i) for i in order]  # sorted: already a heap
    waiting: dict[int, Evaluation] = {}  # collision-free and judged, back in line at the exact prior
    cap = opts.max_feasible_per_target
    while heap and not (opts.max_feasible and len(feasible) >= opts.max_feasible):
        _, i = heapq.heappop(heap)
        c = candidates[i]
        if verdict[i] is not None or (cap and per_target[c.target] >= cap):
            continue
        ev = waiting.pop(i, None)
        if ev is None:
            t = targets[c.target]
            ev = _tool_collisions(c, poses[i], t, world, opts)
            if ev is not None:
                verdict[i] = ev
                continue
            q_i, ok_i = _solve_ik(np.array([i]), poses, tcp_from_flange, arm, reject)
            if i not in q_i:  # rejected by IK
                continue
            ev = _arm_collisions(c, poses[i], q_i[i], ok_i[i], t, world, home_q)
            if not ev.feasible:
                verdict[i] = ev
                continue
            if opts.mechanics is not None:
                # mechanics on the fitted template (friction cones, pad area, weight and torque; the cup's seal and
                # load): candidates that will not hold are rejected; the rest rank by the predicted success times
                # the geometric quality
                mech = judge(
                    c.scheme, t.mesh, t.mass_kg, t.world_from_object, g[i], tool, opts.mechanics, t.measured_points
                )
                if not mech.ok:
                    reject(i, mech.reason, "grasp")
                    continue
                success[i] = mech.success * c.quality
                exact = (
                    opts.w_height * heights[i]
                    + opts.w_quality * success[i]
                    + opts.w_approach * (-approach[i, 2])
                    + opts.w_priority * priorities[i]
                )
                if exact < prior[i]:
                    prior[i] = exact
                    waiting[i] = ev
                    heapq.heappush(heap, (-float(exact), i))
                    continue
        ev = _with_score(ev, float(prior[i]), arm, home_q, world, opts)
        verdict[i] = ev
        feasible.append(ev)
        per_target[c.target] += 1
    final = [
        v if v is not None else Evaluation.rejected(candidates[i], "not_evaluated", "", poses[i], prior=prior[i])
        for i, v in enumerate(verdict)
    ]
    counts = Counter(v.reason for v in final if not v.feasible)
    ranked = tuple(sorted(feasible, key=lambda e: -e.score))
    return EvaluationResult(tuple(final), ranked, dict(counts))


def _solve_ik(
    idx: IntArray,
    poses: FloatArray,
    tcp_from_flange: FloatArray,
    arm: ArmModel,
    reject: Callable[[int, str, str], None],
) -> tuple[dict[int, FloatArray], dict[int, FloatArray]]:
    """IK of candidates `idx` at their five poses on all 8 branches, one batch: per candidate index the unwrapped
    angles (5, 8, 6) and the valid branches (5, 8); candidates without a branch valid at all five poses are
    rejected ('ik' with the pose, 'ik' 'branch_change', 'joint_limits') and left out."""
    q_out: dict[int, FloatArray] = {}
    ok_out: dict[int, FloatArray] = {}
    flange = poses[idx] @ tcp_from_flange
    q, exists, _ = arm.ik_reasons(flange.reshape(-1, 4, 4))
    q = q.reshape(len(idx), 5, 8, 6)
    exists = exists.reshape(len(idx), 5, 8)
    q_unwrapped = _unwrap_branches(q, arm)
    for k, j in enumerate(idx):
        has = exists[k].any(axis=1)
        if not has.all():
            reject(int(j), "ik", POSE_NAMES[int(np.argmin(has))])
            continue
        # a branch must exist at all five poses (straight lines stay on one branch)
        branch_ok = exists[k].all(axis=0)
        if not branch_ok.any():
            reject(int(j), "ik", "branch_change")
            continue
        q_k = q_unwrapped[k]
        lim_ok = np.all((q_k >= arm.lower - 1e-9) & (q_k <= arm.upper + 1e-9), axis=(0, 2)) & branch_ok
        if not lim_ok.any():
            reject(int(j), "joint_limits", "grasp")
            continue
        q_out[int(j)] = q_k
        ok_out[int(j)] = np.broadcast_to(lim_ok[None, :], (5, 8))
    return q_out, ok_out


def _raise_grasps(
    idx: IntArray,
    g: FloatArray,
    approach: FloatArray,
    openings: FloatArray,
    target_idx: FloatArray,
    targets: list[Target],
    world: CollisionWorld,
    tool: object,
    opts: EvaluationOptions,
) -> dict[int, FloatArray]:
    """Grasp poses (4, 4) by candidate index for the parallel grasps among `idx` whose tool, pushed `tip_margin_m`
    further along the approach, overlaps a cell box at the grasp while a pose raised back along the approach by at
    most `max_raise_m` is clear and still reaches `min_contact_m` into the part. Unchanged candidates are left out
    (a hit with no clear raise is rejected by the cell test that follows)."""
    out: dict[int, FloatArray] = {}
    if getattr(tool, "kind", "") != "parallel" or opts.max_raise_m <= 0 or opts.raise_step_m <= 0:
        return out
    tip = float(getattr(tool, "finger_depth_m", 0.0))

    def shifted_by(rows: IntArray, back: FloatArray) -> FloatArray:
        p = g[rows].copy()
        p[:, :3, 3] += approach[rows] * (opts.tip_margin_m - np.asarray(back, dtype=np.float64))[..., None]
        return p

    hit = world.tool_box_hits(shifted_by(idx, np.zeros(len(idx))), openings[idx])
    todo = idx[hit]
    if len(todo) == 0:
        return out
    # depth of the jaw tips past the approached face of the part (its smallest extent along the approach)
    face = np.empty(len(todo))
    need = np.empty(len(todo))
    for t in np.unique(target_idx[todo]):
        rows = target_idx[todo] == t
        tgt = targets[int(t)]
        verts = np.asarray(tgt.mesh.vertices, dtype=np.float64) @ tgt.world_from_object[:3, :3].T  # type: ignore[attr-defined]
        verts = verts + tgt.world_from_object[:3, 3]
        along = approach[todo[rows]] @ verts.T
        face[rows] = along.min(axis=1)
        # thin parts: the jaws must reach down `min_contact_share` of the part's depth along the approach, the depth
        # measured along the template box axis nearest the approach (a plate fitted 2 degrees off flat is still
        # 8 mm thick under the jaws, not 8 mm plus the rise of its far corners)
        lo_b, hi_b = np.asarray(tgt.mesh.bounds, dtype=np.float64)  # type: ignore[attr-defined]
        axis_depth = np.abs(approach[todo[rows]] @ tgt.world_from_object[:3, :3]) * (hi_b - lo_b)
        need[rows] = np.minimum(opts.min_contact_m, opts.min_contact_share * axis_depth.max(axis=1))
    tip_depth = np.einsum("ni,ni->n", g[todo, :3, 3], approach[todo]) + tip - face - need
    # smallest clear raise in whole steps, by bisection (raising along the approach only moves the tips off the
    # surface underneath): the largest allowed raise first, then halving the bracket of each candidate at once
    hi = np.floor(np.minimum(opts.max_raise_m, tip_depth) / opts.raise_step_m + 1e-9).astype(np.int64)
    keep = hi >= 1
    todo, hi = todo[keep], hi[keep]
    if len(todo) == 0:
        return out
    clear = np.logical_not(world.tool_box_hits(shifted_by(todo, hi * opts.raise_step_m), openings[todo]))
    todo, hi = todo[clear], hi[clear]
    lo = np.zeros(len(todo), dtype=np.int64)
    while len(todo) and np.any(hi - lo > 1):
        open_ = hi - lo > 1
        mid = np.where(open_, (lo + hi) // 2, hi)
        rows = np.flatnonzero(open_)
        ok = np.logical_not(
            world.tool_box_hits(shifted_by(todo[rows], mid[rows] * opts.raise_step_m), openings[todo[rows]])
        )
        hi[rows[ok]] = mid[rows[ok]]
        lo[rows[~ok]] = mid[rows[~ok]]
    for j, k in zip(todo, hi, strict=True):
        p = g[j].copy()
        p[:3, 3] -= approach[j] * (k * opts.raise_step_m)
        out[int(j)] = p
    return out


def _unwrap_branches(q: FloatArray, arm: ArmModel) -> FloatArray:
    """(M, 5, 8, 6): `_unwrap_branch` for M candidates at once."""
    two_pi = 2 * np.pi
    ref = q[:, 2:3]
    out = q + two_pi * np.round((ref - q) / two_pi)
    for shift in (two_pi, -two_pi):
        moved = out + shift
        inside_now = np.all((out >= arm.lower) & (out <= arm.upper), axis=1)  # (M, 8, 6)
        inside_moved = np.all((moved >= arm.lower) & (moved <= arm.upper), axis=1)
        take = ~inside_now & inside_moved
        out = np.where(take[:, None], moved, out)
    return out


def _unwrap_branch(q: FloatArray, arm: ArmModel) -> FloatArray:
    """(5, 8, 6): every pose's branch angles shifted by 2 pi multiples next to the grasp pose's (index 2)."""
    out = q.copy()
    ref = q[2]
    two_pi = 2 * np.pi
    for p in range(5):
        out[p] = q[p] + two_pi * np.round((ref - q[p]) / two_pi)
    # shift the whole branch by 2 pi per joint where that brings it inside the limits
    for shift in (two_pi, -two_pi):
        moved = out + shift
        inside_now = np.all((out >= arm.lower) & (out <= arm.upper), axis=0)  # (8, 6)
        inside_moved = np.all((moved >= arm.lower) & (moved <= arm.upper), axis=0)
        take = ~inside_now & inside_moved
        out = np.where(take[None], moved, out)
    return out


def _tool_collisions(
    c: GraspCandidate, poses: FloatArray, target: Target, world: CollisionWorld, opts: EvaluationOptions
) -> Evaluation | None:
    """The rejection of candidate `c` by the tool alone (fcl), or None: the tool at the grasp pose itself against
    everything but the target (and against the neighbours grown by the noise margin), then backed off a little
    against the target too (suction cups and jaw pads touch it by design), at pre-grasp and at entry."""
    with world.without(target.name):
        hit = world.check_tool(poses[2], c.opening_m)
        if hit is None and opts.noise_margin:  # neighbours (not the cell: its boxes are exact) with the noise margin
            hit = world.check_tool(poses[2], c.opening_m, skip=("cell",), margin=True)
    if hit is not None:
        return Evaluation.rejected(c, hit.reason, "grasp", poses)
    a = poses[2][:3, 2]
    backed = poses[2].copy()
    backed[:3, 3] -= a * opts.contact_backoff_m
    for pose_name, pose in (("grasp", backed), ("pre_grasp", poses[1]), ("entry", poses[0])):
        hit = world.check_tool(pose, c.opening_m)
        if hit is not None:
            return Evaluation.rejected(c, hit.reason, pose_name, poses)
    return None


def _arm_collisions(
    c: GraspCandidate,
    poses: FloatArray,
    q: FloatArray,
    ok: FloatArray,
    target: Target,
    world: CollisionWorld,
    home_q: FloatArray,
) -> Evaluation:
    """The arm on each valid branch (nearest to home first) at all five poses, the target held (attached, removed
    from the world) at lift and exit: feasible on the first clear branch, else the first branch's hit."""
    branches = np.flatnonzero(ok[0]) if ok.ndim == 2 else np.flatnonzero(ok)
    travel = [float(np.abs(q[0, b] - home_q).sum()) for b in branches]
    first_hit: tuple[Hit, str] | None = None
    for b in (branches[j] for j in np.argsort(travel)):
        hit, pose_name = _arm_at_poses(q[:, b], c, target, poses, world)
        if hit is None:
            return Evaluation(c, True, "", "", poses, q[:, b].copy(), int(b))
        if first_hit is None:
            first_hit = (hit, pose_name)
    if first_hit is None:
        return Evaluation(c, False, "ik", "branch_change", poses)
    return Evaluation(c, False, first_hit[0].reason, first_hit[1], poses)


def _arm_at_poses(
    q: FloatArray, c: GraspCandidate, target: Target, poses: FloatArray, world: CollisionWorld
) -> tuple[Hit | None, str]:
    """First hit of the arm at entry, pre-grasp, grasp (empty-handed) and of arm, tool and held target at lift and
    exit, on one branch q (5, 6); fcl runs only where the bounding spheres cannot prove a pose clear."""
    from normpos_grasp.collision.world import held_radius  # fcl stays out of this module's import

    tcp_from_object = invert_pose(poses[2]) @ target.world_from_object
    if world.held_name:
        clear = world.configs_clear(q[:3], c.opening_m)
    else:  # one sphere pass: empty-handed at entry, pre-grasp and grasp, holding the target at lift and exit
        clear = world.configs_clear(q, c.opening_m, _HELD_ROWS, tcp_from_object, target.name, held_radius(target.mesh))
    for p in (2, 1, 0):  # grasp first: the most constrained
        hit = None if clear[p] else world.check_arm(q[p])
        if hit is not None:
            return hit, POSE_NAMES[p]
    if len(clear) == 5 and clear[3] and clear[4]:
        return None, ""
    with world.holding(target.name, target.mesh, tcp_from_object):  # type: ignore[arg-type]
        if len(clear) == 3:
            clear = np.concatenate([clear, world.configs_clear(q[3:], c.opening_m)])
        for p in (3, 4):
            hit = None if clear[p] else world.check_config(q[p], c.opening_m)
            if hit is not None:
                return hit, POSE_NAMES[p]
    return None, ""


_HELD_ROWS = np.array([False, False, False, True, True])


def _with_score(
    ev: Evaluation, prior: float, arm: ArmModel, home_q: FloatArray, world: CollisionWorld, opts: EvaluationOptions
) -> Evaluation:
    if ev.q is None or ev.world_from_tcp is None:
        return ev
    travel = float(np.abs(ev.q[0] - home_q).sum())
    clear = 0.0
    if opts.clearance:
        clear = 1.0 if world.check_tool(ev.world_from_tcp[1], ev.candidate.opening_m, inflated=True) is None else 0.0
    score = prior - opts.w_travel * travel + opts.w_clearance * clear
    return Evaluation(ev.candidate, True, "", "", ev.world_from_tcp, ev.q, ev.branch, score, prior)
