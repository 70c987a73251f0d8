"""Equivalent arm configurations of a pick-and-place and the quickest among them.

A grasp can be reached with joint 6 moved by a multiple of pi: an even multiple is the same flange pose (a 2 pi
copy), an odd one turns the TCP frame half a turn about its approach axis, the same physical grasp when the tool's
collision shapes are half-turn symmetric and the TCP lies on the flange axis (two-jaw grippers, round cups). A
place can be reached through every TCP pose that leaves the part where the planned one does (the part's symmetries
about a vertical axis: a box turned half a turn lands the same) and, where the place does not align the part, the
tool's half turn (the part then lands as it was grasped by a tool that looks the same). The choice among them is
the one with the shortest estimated joint motion (`timing.joint_motion_s`): a wrist turned 3 rad the long way
costs a second of cycle time.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.planning.timing import joint_motion_s, rest_to_rest_s
from normpos_grasp.records.plan import Evaluation
from normpos_grasp.records.tool import ToolModel, ToolShape
from normpos_grasp.typing import FloatArray

#: the TCP frame turned half a turn about its z (approach) axis
HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])

Caps = tuple[FloatArray, FloatArray, FloatArray]


def half_turn_symmetric(tool: ToolModel, tol: float = 1e-6) -> bool:
    """Whether `tool` looks the same turned half a turn about its TCP z axis: the TCP z axis is the flange axis (the
    turn is joint 6 moved by pi) and its collision shapes at the smallest and the largest opening map onto each
    other (boxes up to their axes' signs, cylinders and capsules up to their axis' sign, spheres by their centre)."""
    flange_from_tcp = np.asarray(tool.flange_from_tcp, dtype=np.float64)
    if np.abs(flange_from_tcp[:3, 2] - [0.0, 0.0, 1.0]).max() > tol or np.abs(flange_from_tcp[:2, 3]).max() > tol:
        return False
    for opening in (tool.min_opening_m, tool.stroke_m):
        shapes = tool.posed_shapes(opening)
        used: set[int] = set()
        for s, pose in shapes:
            turned = HALF_TURN @ pose
            match = next(
                (i for i, (o, o_pose) in enumerate(shapes) if i not in used and _same_shape(s, turned, o, o_pose, tol)),
                None,
            )
            if match is None:
                return False
            used.add(match)
    return True


def _same_shape(s: ToolShape, pose: FloatArray, o: ToolShape, o_pose: FloatArray, tol: float) -> bool:
    if o.kind != s.kind or len(o.size) != len(s.size) or np.abs(np.subtract(o.size, s.size)).max() > tol:
        return False
    if np.abs(o_pose[:3, 3] - pose[:3, 3]).max() > tol:
        return False
    if s.kind == "sphere":
        return True
    if s.kind == "box":
        return bool(np.abs(np.abs(o_pose[:3, :3].T @ pose[:3, :3]) - np.eye(3)).max() <= tol)
    return bool(abs(abs(float(o_pose[:3, 2] @ pose[:3, 2])) - 1.0) <= tol)


def quickest_grasp(
    ev: Evaluation,
    arm: ArmModel,
    flange_from_tcp: FloatArray,
    home: FloatArray,
    caps: Caps,
    turn_ok: bool,
    arm_clear: Any,
) -> Evaluation:
    """`ev` or the equivalent evaluation with joint 6 moved by k pi (|k| <= 3) at all five poses (odd k only with
    `turn_ok`: the candidate's and the poses' TCP frames turned half a turn) with the shortest estimated
    home -> entry motion; every variant stays within the joint limits at the five poses (0.2 rad margin on joint
    6 for the lines between them) and passes `arm_clear(q (6,)) -> bool` at entry, pre-grasp and grasp."""
    if ev.q is None or ev.world_from_tcp is None:
        return ev
    best, best_t = ev, joint_motion_s(home, ev.q[0], caps)
    margin = np.zeros(6)
    margin[5] = 0.2
    for k in (-3, -2, -1, 1, 2, 3):
        if k % 2 and not turn_ok:
            continue
        q = ev.q.copy()
        q[:, 5] += k * np.pi
        if np.any(q < arm.lower + margin) or np.any(q > arm.upper - margin):
            continue
        t = joint_motion_s(home, q[0], caps)
        if t >= best_t - 1e-3:
            continue
        poses = ev.world_from_tcp @ HALF_TURN if k % 2 else ev.world_from_tcp
        if np.abs(arm.fk(q) @ flange_from_tcp - poses).max() > 1e-6:  # the turn is not joint 6 alone
            continue
        if not all(arm_clear(q[p]) for p in (0, 1, 2)):
            continue
        cand = ev.candidate
        if k % 2:
            cand = replace(cand, world_from_tcp=np.asarray(cand.world_from_tcp) @ HALF_TURN)
        best, best_t = replace(ev, candidate=cand, world_from_tcp=poses, q=q), t
    return best


def place_poses(
    place_pose: FloatArray, tcp_from_object: FloatArray, vertices: FloatArray, turn_ok: bool, tol_m: float = 1e-4
) -> list[FloatArray]:
    """TCP poses at release (4, 4) equivalent to `place_pose`, it first: with `turn_ok` the TCP turned half a turn
    about its axis; and, for a vertical approach, the TCP turned a quarter, half or three quarters about the
    vertical through the placed part's centre (the centre of its vertices' box), kept where the part's vertices
    (N, 3, object frame) land within `tol_m` of those of the placement `place_pose` (or, with `turn_ok`, its
    turn) makes."""
    refs = [place_pose] + ([place_pose @ HALF_TURN] if turn_ok else [])
    out = list(refs)
    verts = np.asarray(vertices, dtype=np.float64)

    def placed(tcp: FloatArray) -> FloatArray:
        obj = tcp @ tcp_from_object
        return verts @ obj[:3, :3].T + obj[:3, 3]

    if abs(float(place_pose[2, 2])) < 1.0 - 1e-6:  # a slanted approach keeps its direction
        return out
    from scipy.spatial import cKDTree

    trees = [cKDTree(placed(r)) for r in refs]
    world = placed(place_pose)
    centre = 0.5 * (world.min(axis=0) + world.max(axis=0))
    for quarter in (1, 2, 3):
        c, s = np.cos(quarter * np.pi / 2), np.sin(quarter * np.pi / 2)
        turn = np.eye(4)
        turn[:2, :2] = [[c, -s], [s, c]]
        turn[:2, 3] = centre[:2] - turn[:2, :2] @ centre[:2]
        for r in refs:
            pose = turn @ r
            pts = placed(pose)
            if any(float(tree.query(pts)[0].max()) <= tol_m for tree in trees):
                out.append(pose)
    return out


#: summed joint change that counts as much as a second of estimated motion when ranking place configurations, rad:
#: between configurations of about the same time the one that moves the joints less (no elbow flipped over)
RAD_PER_S = 10.0


def ranked_place_configs(
    poses: list[FloatArray],
    approach_m: float,
    q_from: FloatArray,
    arm: ArmModel,
    tcp_from_flange: FloatArray,
    caps: Caps | None,
) -> list[tuple[FloatArray, FloatArray, FloatArray, int]]:
    """(place pose, pre-place pose (`approach_m` back along the TCP z axis), pre-place joints (6,), IK branch) of
    every reachable branch (2 pi copy nearest `q_from`) of every pose in `poses`, best first: by estimated joint
    motion time from `q_from` (`timing.joint_motion_s` within `caps`) plus the summed joint change / RAD_PER_S;
    without caps by the summed joint change alone (the nearest branch)."""
    if not poses:
        return []
    pres = np.stack(poses)
    pres[:, :3, 3] -= pres[:, :3, 2] * approach_m
    # one IK batch for every pose; the costs of all reachable branches in one pass (elementwise: the same floats as
    # pose by pose and branch by branch)
    q_all, ok_all = arm.ik(pres @ tcp_from_flange, q_from)
    rows, branches = np.nonzero(ok_all)
    q_reach = q_all[rows, branches]  # (M, 6)
    change = [float(np.abs(q - q_from).sum()) for q in q_reach]
    motion = np.max(rest_to_rest_s(q_reach - q_from, *caps), axis=1) if caps is not None and len(q_reach) else None
    out: list[tuple[float, int, FloatArray, FloatArray, FloatArray, int]] = []
    for m, (i, b) in enumerate(zip(rows, branches, strict=True)):
        cost = change[m] if motion is None else float(motion[m]) + change[m] / RAD_PER_S
        out.append((cost, int(i), poses[int(i)], pres[int(i)], q_reach[m], int(b)))
    out.sort(key=lambda r: (r[0], r[1]))
    return [(pose, pre, q, b) for _, _, pose, pre, q, b in out]
