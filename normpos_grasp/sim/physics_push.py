"""Physics of a nudge: the closed gripper descends beside a part and pushes it sideways (MuJoCo).

A bin-picking cell that finds no feasible grasp can move parts instead of stopping: a part pressed against a
wall, standing in a corner or wedged between neighbours is pushed a few centimetres, and the next frame is
perceived anew. `simulate_push` replays such a push against the TRUE part poses with the same hand, parts and
cell geometry as `physics.validate_grasp` and returns where every part came to rest, and whether the hand hit
the cell (a real arm would stop: 'collision'). Metres, seconds, newtons; deterministic.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from normpos_grasp.errors import InputError, SimulationError
from normpos_grasp.geometry.transforms import make_pose
from normpos_grasp.records.template import Template
from normpos_grasp.sim.physics import (
    GripperSpec,
    PhysicsOptions,
    StaticBox,
    _hand_scene_xml,
    _hand_xml,
    _min_jerk,
    _Monitor,
    _object_body_xml,
    _quat_wxyz,
    _static_geoms,
    collision_pieces,
)
from normpos_grasp.typing import FloatArray
from normpos_grasp.validation import as_float_array, check_pose

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PushOptions:
    """Motion of a push. descend_m / descend_s: straight vertical descent onto the start pose, m / s. push_s:
    duration of the push (minimum-jerk). rise_m / rise_s: the hand rises straight up afterwards. settle_s: the
    parts come to rest. Contact limits and friction come from `physics` (PhysicsOptions)."""

    descend_m: float = 0.08
    descend_s: float = 0.4
    push_s: float = 0.8
    rise_m: float = 0.08
    rise_s: float = 0.3
    settle_s: float = 0.4
    physics: PhysicsOptions = PhysicsOptions()


@dataclass(frozen=True, eq=False)
class PushResult:
    """outcome: 'pushed' or 'collision' (the hand hit the cell harder than the physics limits; parts are where
    they came to rest anyway). collision_with: what it hit. world_from_objects_final: (N, 4, 4) final poses.
    moved_m: (N,) how far each part's origin moved. sim_time_s: simulated time."""

    outcome: str
    collision_with: str
    world_from_objects_final: FloatArray
    moved_m: FloatArray
    sim_time_s: float


def simulate_push(
    objects: list[tuple[Template, FloatArray]] | tuple[tuple[Template, FloatArray], ...],
    static_boxes: list[StaticBox] | tuple[StaticBox, ...],
    gripper: GripperSpec,
    world_from_tcp: FloatArray,
    push_m: FloatArray,
    options: PushOptions | None = None,
) -> PushResult:
    """Push with the closed gripper: descend `descend_m` straight down onto `world_from_tcp` (4, 4), move by
    `push_m` (3,) metres, rise and let the parts settle. objects: every part with its true pose (free bodies);
    static_boxes: the cell as in `validate_grasp` (a floor under the lowest part when empty)."""
    import mujoco

    opts = options or PushOptions()
    phys = opts.physics
    w_tcp = check_pose(world_from_tcp, "world_from_tcp", tol=1e-5)
    push = as_float_array(push_m, "push_m", (3,))
    if not objects:
        raise InputError("simulate_push needs at least one part to push")
    assets: list[str] = []
    bodies = []
    poses = []
    lowest = np.inf
    for i, (tmpl, pose_in) in enumerate(objects):
        pose = check_pose(pose_in, f"objects[{i}] pose", tol=1e-5)
        poses.append(pose)
        lowest = min(lowest, float((np.asarray(tmpl.mesh.vertices) @ pose[:3, :3].T + pose[:3, 3])[:, 2].min()))
        pieces = collision_pieces(tmpl, phys.decomposition)
        bodies.append(_object_body_xml(f"part{i}", tmpl, pose, pieces, phys.object_friction, assets))
    statics = _static_geoms(static_boxes, phys.static_friction, lowest)
    pre = w_tcp.copy()
    pre[2, 3] += opts.descend_m
    closed = 1e-3  # jaws (nearly) closed: the fingers form one pusher
    hand, actuators, exclude, coupling = _hand_xml(gripper, pre, closed)
    xml = _hand_scene_xml("push", phys.timestep_s, assets, statics + bodies, hand, pre, exclude, actuators, coupling)
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise SimulationError(f"MuJoCo rejected the push scene: {exc}") from exc
    data = mujoco.MjData(model)
    # contact groups of physics._Monitor: parts are 'target' (1, the hand may push them), the cell is 0
    groups = np.zeros(model.ngeom, dtype=np.int64)
    names = []
    hand_body = model.body("hand").id
    for gid in range(model.ngeom):
        body = int(model.geom_bodyid[gid])
        root = int(model.body_rootid[body])
        groups[gid] = 3 if root == hand_body else (1 if body != 0 else 0)
        names.append(model.geom(gid).name or f"geom{gid}")
    monitor = _Monitor(groups, names)
    if gripper.kind == "parallel":
        q0 = (gripper.stroke_m - closed) / 2.0
        for side in ("left", "right"):
            data.qpos[model.joint(f"jaw_{side}").qposadr[0]] = q0
            data.ctrl[model.actuator(f"drive_{side}").id] = q0
    mujoco.mj_forward(model, data)
    mocap = int(model.body("hand_mocap").mocapid[0])
    data.mocap_quat[mocap] = _quat_wxyz(w_tcp[:3, :3])
    start, top = w_tcp[:3, 3].copy(), pre[:3, 3].copy()
    end = start + push
    rise = np.array([0.0, 0.0, opts.rise_m])
    phases = [
        ("descend", opts.descend_s, lambda s: top + (start - top) * _min_jerk(s)),
        ("push", opts.push_s, lambda s: start + push * _min_jerk(s)),
        ("rise", opts.rise_s, lambda s: end + rise * _min_jerk(s)),
        ("settle", opts.settle_s, lambda s: end + rise),
    ]
    dt = phys.timestep_s
    steps = 0
    for _name, duration, path in phases:
        n = max(1, int(round(duration / dt)))
        for k in range(n):
            data.mocap_pos[mocap] = path((k + 1) / n)
            mujoco.mj_step(model, data)
            steps += 1
            if steps % phys.check_every == 0:
                monitor.check(data, phys, target_counts=False)
        if not np.all(np.isfinite(data.qpos)):
            raise SimulationError("the push simulation diverged; reduce timestep_s")
    final = np.empty((len(objects), 4, 4))
    for i in range(len(objects)):
        bid = model.body(f"part{i}").id
        final[i] = make_pose(np.asarray(data.xmat[bid]).reshape(3, 3), np.asarray(data.xpos[bid]))
    moved = np.linalg.norm(final[:, :3, 3] - np.array(poses)[:, :3, 3], axis=1)
    outcome = "collision" if monitor.collision else "pushed"
    logger.debug("push %s: parts moved up to %.3f m (%s)", outcome, float(moved.max()), monitor.collision)
    return PushResult(outcome, monitor.collision, final, moved, steps * dt)
