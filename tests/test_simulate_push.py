"""Physics of a nudge: the closed gripper pushes a part sideways; pushing the hand into the cell is a collision."""

from __future__ import annotations

import mujoco  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import pytest
import trimesh

from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import make_pose
from normpos_grasp.records.template import Template
from normpos_grasp.sim.physics import GripperSpec
from normpos_grasp.sim.physics_push import simulate_push

TABLE = [("table", make_pose(translation=[0.0, 0.0, -0.025]), np.array([1.0, 1.0, 0.05]))]
DOWN = np.column_stack([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # approach -z, jaws close along y


def _cube() -> Template:
    return Template("cube", "cube", trimesh.creation.box(extents=(0.04, 0.04, 0.04)), shape="box", mass_kg=0.09)


def test_push_moves_the_part_along_the_push() -> None:
    cube = _cube()
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    spec = GripperSpec.preset("2f85")
    # jaw tips 1.3 cm above the table, the closed fingers 1 cm behind the cube's -x face
    start = make_pose(DOWN, [-0.02 - spec.finger_width_m / 2.0 - 0.01, 0.0, 0.013 + spec.tip_beyond_tcp_m])
    res = simulate_push([(cube, pose)], TABLE, spec, start, np.array([0.06, 0.0, 0.0]))
    assert res.outcome == "pushed" and res.collision_with == ""
    moved = res.world_from_objects_final[0][:3, 3] - pose[:3, 3]
    assert 0.02 < moved[0] < 0.07 and abs(moved[1]) < 0.01 and abs(moved[2]) < 0.005  # slid, still upright
    again = simulate_push([(cube, pose)], TABLE, spec, start, np.array([0.06, 0.0, 0.0]))
    assert np.array_equal(again.world_from_objects_final, res.world_from_objects_final)  # deterministic


def test_pushing_into_the_cell_is_a_collision() -> None:
    cube = _cube()
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    wall = ("wall", make_pose(translation=[0.1, 0.0, 0.05]), np.array([0.01, 0.4, 0.1]))
    spec = GripperSpec.preset("2f85")
    start = make_pose(DOWN, [0.05, 0.0, 0.013 + spec.tip_beyond_tcp_m])
    res = simulate_push([(cube, pose)], [*TABLE, wall], spec, start, np.array([0.08, 0.0, 0.0]))
    assert res.outcome == "collision" and "wall" in res.collision_with
    assert res.moved_m[0] < 0.005  # the cube was not in the way


def test_push_needs_parts() -> None:
    with pytest.raises(InputError):
        simulate_push([], TABLE, GripperSpec.preset("2f85"), np.eye(4), np.zeros(3))
