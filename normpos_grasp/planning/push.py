"""Pushes planned on the perceived scene: when no grasp is feasible, slide or tip a part so that one becomes feasible.

A push is planned from the fits and the measured points only (never from true poses): the closed gripper descends
beside a perceived object's far side and pushes it horizontally towards the bin centre and away from its neighbours.
`normpos-grasp simulate` replays it in MuJoCo on the true scene (`sim.physics_push`); a cell would run it as two
linear moves.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.planning.plan import PlanOptions, build_world
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.plan import PickPlan, Trajectory
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.typing import FloatArray


@dataclass(frozen=True)
class PushHand:
    """The closed parallel gripper as a pusher, m: how far the fingertips reach past the TCP along +z, and the
    finger's width (across the closing direction) and thickness (along it)."""

    tip_beyond_tcp_m: float
    finger_width_m: float
    finger_thickness_m: float


@dataclass(frozen=True)
class Push:
    """A planned push: the closed gripper's start pose `world_from_tcp` (4, 4) and the horizontal push (3,), m.
    kind: 'push' (the fingers beside the part) or 'drag' (`planning.drag`: the fingertips pressed `press_m` metres
    into the part's top, sliding it along)."""

    world_from_tcp: FloatArray
    push: FloatArray
    kind: str = "push"
    press_m: float = 0.0


def perceived_world(
    cell: CellConfig, fits: Sequence[TemplateFit], normpositions: Sequence[NormPosition]
) -> tuple[Any, ArmModel]:
    """The collision world of a nudge (push or drag), from the perceived scene only: the cell, the fits and the
    unexplained measured points (unmatched objects kept), with the cell's arm and tool set; and that arm."""
    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    world, _, _ = build_world(cell, list(fits), list(normpositions), arm, PlanOptions(pick_unmatched=True))
    world.set_arm(arm)
    world.set_tool(cell.tool)
    world.update()
    return world, arm


def plan_push(
    plan: PickPlan,
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition],
    cell: CellConfig,
    hand: PushHand,
    floor_z: float,
    push_m: float,
) -> Push | None:
    """A push from the perceived scene only (fits and measured points, never the true poses): for the perceived
    objects, highest first, and horizontal directions ranked towards the bin centre and away from the nearest
    neighbours, the closed gripper's start pose beside the object's far side (jaw tips at a third of its height,
    at least 6 mm above the floor; then at three quarters in any direction, tipping it over) must be clear of
    everything from 8 cm above down to the start (jaws closing across or along the push), and the hand must stay
    clear of the cell over the push (`push_m`, else half of it).
    `floor_z`: the bin floor's height, m. Returns the push, or None when no perceived object can be pushed."""
    return next(push_candidates(plan, fits, normpositions, cell, hand, floor_z, push_m), None)


def push_candidates(
    plan: PickPlan,
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition],
    cell: CellConfig,
    hand: PushHand,
    floor_z: float,
    push_m: float,
) -> Iterator[Push]:
    """Every push `plan_push` would accept, best first (one per object and direction; `plan_push` takes the
    first). A caller that also plans the arm's path (`judged_push_motion`) takes the next when that one has none."""
    targets = list(plan.targets)
    if not targets:
        return
    if cell.bin is None:
        raise InputError("planning a push needs a cell with a bin")
    world, _ = perceived_world(cell, fits, normpositions)
    tip = float(getattr(cell.tool, "finger_depth_m", 0.0) or hand.tip_beyond_tcp_m)
    half_width = hand.finger_width_m / 2.0
    bin_xy = np.asarray(cell.bin.world_from_bin, dtype=np.float64)[:2, 3]
    geo = []
    for t in targets:
        verts = np.asarray(t.mesh.vertices, dtype=np.float64) @ t.world_from_object[:3, :3].T  # type: ignore[attr-defined]
        verts = verts + t.world_from_object[:3, 3]
        geo.append((verts, verts.mean(axis=0)))
    order = sorted(range(len(targets)), key=lambda k: -float(geo[k][0][:, 2].max()))
    angles = np.arange(8) * (np.pi / 4.0)
    dirs = np.column_stack([np.cos(angles), np.sin(angles), np.zeros(8)])
    for k in order:
        verts, c = geo[k]
        pref = bin_xy - c[:2]
        pref = pref / max(float(np.linalg.norm(pref)), 1e-9)
        for j, (_, cj) in enumerate(geo):
            d = c[:2] - cj[:2]
            dist = float(np.linalg.norm(d))
            if j != k and 1e-6 < dist < 0.12:
                pref = pref + d / dist
        norm = max(float(np.linalg.norm(pref)), 1e-9)
        ranked = [
            m for m in sorted(range(8), key=lambda m: -float(dirs[m, :2] @ pref)) if dirs[m, :2] @ pref > -0.2 * norm
        ]
        low, high = float(verts[:, 2].min()), float(verts[:, 2].max())
        # jaw tips at a third of the part's height (slide it), else at three quarters (tip it over)
        heights = [max(floor_z + 0.006, low + (high - low) * f) for f in (1.0 / 3.0, 0.75)]
        everywhere = sorted(range(8), key=lambda m: -float(dirs[m, :2] @ pref))  # tipping over: any way it falls
        tries = [(m, heights[0]) for m in ranked] + [(m, heights[1]) for m in everywhere]
        for (m, tip_z), across in itertools.product(tries, (True, False)):
            d = dirs[m]
            back = float(c @ d - (verts @ d).min())
            # jaws closing across the push (a 4 cm wide pusher) or along it (the palm's long side along the push)
            x = np.array([-d[1], d[0], 0.0]) if across else d.copy()
            reach = half_width if across else hand.finger_thickness_m
            z = np.array([0.0, 0.0, -1.0])
            start = np.eye(4)
            start[:3, :3] = np.column_stack([x, np.cross(z, x), z])
            start[:3, 3] = [*(c[:2] - d[:2] * (back + reach + 0.01)), tip_z + tip]
            descent = [start.copy() for _ in range(4)]
            for n, lift in enumerate((0.0, 0.02, 0.05, 0.08)):
                descent[n][2, 3] += lift
            if any(world.check_tool(p, 0.0) is not None for p in descent):
                continue
            for dist in (push_m, push_m / 2.0):
                along = []
                for s in np.linspace(0.0, dist, 6)[1:]:
                    p = start.copy()
                    p[:3, 3] += d * s
                    along.append(p)
                if all(world.check_tool(p, 0.0, skip=("object", "clutter")) is None for p in along):
                    yield Push(start, d * dist)
                    break


def push_motion(
    push: Push,
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition],
    cell: CellConfig,
    start_q: FloatArray,
    rise_m: float = 0.08,
) -> Trajectory:
    """The trajectory (within the cell's joint and TCP caps) that carries out `push` with the closed gripper from
    `start_q`: a joint-space move
    (straight when clear, else RRT-Connect) to `rise_m` above the push's start, then straight TCP lines (IK every
    `PlanOptions.cartesian_step_m` on one branch) down to the start, along the push and up by `rise_m`. The arm is
    checked against the perceived world all along, the tool too until the push starts (then against the cell only:
    it touches the parts it moves). Raises PlanningError (with a reason) when some piece has no path."""
    from normpos_grasp.errors import PlanningError
    from normpos_grasp.geometry.transforms import invert_pose
    from normpos_grasp.planning.plan import _ConfigFree, _line, _PathRejected
    from normpos_grasp.planning.rrt import plan_joint_motion

    opts = PlanOptions()
    world, arm = perceived_world(cell, fits, normpositions)
    tcp_from_flange = invert_pose(cell.tool.flange_from_tcp)
    start = np.asarray(push.world_from_tcp, dtype=np.float64)
    above = start.copy()
    above[2, 3] += rise_m
    end = start.copy()
    end[:3, 3] += np.asarray(push.push, dtype=np.float64)
    end_up = end.copy()
    end_up[2, 3] += rise_m
    q0 = np.asarray(start_q, dtype=np.float64)
    q_above, ok = arm.ik(above @ tcp_from_flange, q0)
    branches = np.flatnonzero(ok[0])
    if len(branches) == 0:
        raise _PathRejected("push: the pose above the push is out of reach", "push_ik")
    branches = branches[np.argsort(np.abs(q_above[0, branches] - q0).sum(axis=1))]
    free = _ConfigFree(world, 0.0)
    last: PlanningError = _PathRejected("push: no branch", "push_ik")
    for b in branches:
        try:
            down, _ = _line(arm, tcp_from_flange, above, start, q_above[0, b], int(b), opts)
            along, _ = _line(arm, tcp_from_flange, start, end, down[-1], int(b), opts)
            up, _ = _line(arm, tcp_from_flange, end, end_up, along[-1], int(b), opts)
        except _PathRejected as exc:
            last = exc
            continue
        # a drag presses the fingertips `press_m` into the part it slides: the descent's last `press_m` + 5 mm come
        # into contact with it (the drag planner proved the tool clear of everything above) and are judged like the
        # slide itself
        heights = (arm.fk(down) @ cell.tool.flange_from_tcp)[:, 2, 3] - start[2, 3]
        touching = heights <= push.press_m + 0.005 if push.press_m > 0 else np.zeros(len(down), dtype=bool)
        if not all(free(q) for q, t in zip(down[1:], touching[1:], strict=True) if not t):
            last = _PathRejected("push: collision on the way down", "push_collision")
            continue
        # along the push and on the way up the tool touches the parts it moved (the perceived world no longer
        # holds where they are): the tool is checked against the cell only, the arm against everything
        pushing = np.vstack([down[touching], along, up[1:]])
        if any(world.check_arm(q) is not None for q in pushing) or any(
            world.check_config(q, 0.0, skip=("object", "clutter")) is not None for q in pushing
        ):
            last = _PathRejected("push: collision along the push or on the way up", "push_collision")
            continue
        try:
            transfer = plan_joint_motion(q0, down[0], free, arm.lower, arm.upper, opts.motion)
        except PlanningError as exc:
            last = _PathRejected(f"push: no joint path to the push: {exc}", "push_transfer")
            continue
        from normpos_grasp.planning.timing import time_parameterise

        motion = cell.motion
        moves = [np.stack(transfer[k : k + 2]) for k in range(len(transfer) - 1)]
        lines = [down, along, up]
        fk = arm.fk
        tcps = [(fk(seg) @ cell.tool.flange_from_tcp)[:, :3, 3] for seg in lines]
        return time_parameterise(
            moves + lines,
            np.asarray(motion.joint_velocity, dtype=np.float64),
            np.asarray(motion.joint_acceleration, dtype=np.float64),
            [None] * len(moves) + tcps,
            motion.tcp_speed_m_s,
        )
    raise last


def judged_push_motion(
    push: Push,
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition],
    cell: CellConfig,
    start_q: FloatArray,
) -> Trajectory:
    """`push_motion`, judged by the cell as execution judges a plan (`SafetyLimits.check_path` on the samples as
    plan.json rounds them: joint limits, TCP workspace, joint speed and acceleration caps). Raises PlanningError with
    reason 'push_cell_<check>' when the cell refuses it (and push_motion's reasons when it has no path)."""
    from normpos_grasp.cell.limits import SafetyLimits
    from normpos_grasp.errors import SafetyViolation
    from normpos_grasp.planning.plan import _cell_reason, _PathRejected

    trajectory = push_motion(push, fits, normpositions, cell, start_q)
    t = np.array([round(float(v), 6) for v in trajectory.t])
    q = np.array([[round(float(v), 9) for v in row] for row in trajectory.q])
    try:
        SafetyLimits.from_cell(cell).check_path([f"s{k}" for k in range(len(q))], q, t, q)
    except SafetyViolation as exc:
        raise _PathRejected(f"the cell refuses the {push.kind}: {exc}", _cell_reason("push", exc)) from exc
    return trajectory
