"""Physics validation of grasps in MuJoCo: good grasps hold, known-bad ones fail, runs are deterministic."""

from __future__ import annotations

from dataclasses import replace

import mujoco  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import pytest
import trimesh

from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import make_pose, rotation_from_rotvec
from normpos_grasp.records.template import Template
from normpos_grasp.sim.physics import (
    GripperSpec,
    PhysicsOptions,
    collision_pieces,
    validate_grasp,
)

TABLE = [("table", make_pose(translation=[0.0, 0.0, -0.025]), np.array([1.0, 1.0, 0.05]))]


def _tcp(position: np.ndarray, approach=(0.0, 0.0, -1.0), closing=(1.0, 0.0, 0.0)) -> np.ndarray:
    z = np.asarray(approach, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.asarray(closing, dtype=np.float64)
    x = x - z * (x @ z)
    x /= np.linalg.norm(x)
    return make_pose(np.column_stack([x, np.cross(z, x), z]), position)


def _box(extents, mass=0.1, name="box") -> Template:
    return Template(name=name, label=name, mesh=trimesh.creation.box(extents=extents), shape="box", mass_kg=mass)


def _sphere(radius=0.0225) -> Template:
    return Template(
        "sphere", "sphere", trimesh.creation.icosphere(subdivisions=3, radius=radius), shape="sphere", mass_kg=0.07
    )


def _ring() -> Template:
    mesh = trimesh.creation.annulus(r_min=0.018, r_max=0.03, height=0.015, sections=48)
    return Template("ring", "ring", mesh, shape="ring", mass_kg=0.09)


def test_centred_antipodal_grasp_holds() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    res = validate_grasp(cube, pose, [], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.06)
    assert res.outcome == "held", res.reason
    assert res.slip_m < 2e-3
    assert res.lift_m == pytest.approx(0.1, abs=5e-3)
    assert res.grip_force_n == pytest.approx(2 * 100.0, rel=0.1)  # two fingers at the 100 N force limit
    assert np.linalg.norm(res.object_offset_m) < 3e-3
    assert res.max_penetration_m < 2e-3


def test_part_gripped_across_a_vertical_closing_axis_does_not_drift_with_the_jaws() -> None:
    # Issue 17: a 30 mm thick plate gripped on its top and bottom faces (approach horizontal, closing axis
    # vertical), standing on a narrow post that the fingers straddle. With the two jaws as independent
    # force-saturated servos, the plate and both fingers sank together under gravity (nothing held the pair)
    # until the upper finger neared its stop: 14.8 mm of 'slip' with no motion in the pads. The 2F-85's jaws are
    # coupled, so the plate stays where it was gripped.
    plate = _box((0.04, 0.12, 0.03), mass=0.15, name="plate")
    post = [("post", make_pose(translation=[0.0, 0.0, 0.05]), np.array([0.02, 0.01, 0.1]))]
    pose = make_pose(translation=[0.0, 0.0, 0.115])
    tcp = _tcp(pose[:3, 3] + [-0.008, 0.035, 0.0], approach=(1.0, 0.0, 0.0), closing=(0.0, 0.0, 1.0))
    res = validate_grasp(plate, pose, [], post, GripperSpec.preset("2f85"), tcp, 0.05)
    assert res.outcome == "held", res.reason
    assert res.slip_m < 1e-3
    assert res.grip_force_n == pytest.approx(2 * 100.0, rel=0.1)  # the coupling leaves the squeeze as it was


def test_fingers_on_sphere_pole_fail() -> None:
    sphere = _sphere()
    pose = make_pose(translation=[0.0, 0.0, 0.0225])
    # 2F-85 fingertips reach 13 mm past the TCP: they close on the pole cap, 4 mm below its top
    tcp = _tcp(pose[:3, 3] + [0.0, 0.0, 0.0225 - 0.004 + 0.013])
    res = validate_grasp(sphere, pose, [], TABLE, GripperSpec.preset("2f85"), tcp, 0.065)
    assert res.outcome in ("slip", "drop"), res.reason
    # the same sphere gripped across its equator holds
    good = validate_grasp(sphere, pose, [], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.065)
    assert good.outcome == "held", good.reason


def test_suction_on_ring_hole_drops_and_on_flat_face_holds() -> None:
    ring = _ring()
    pose = make_pose(translation=[0.0, 0.0, 0.0075])
    suction = GripperSpec.preset("suction")
    hole = validate_grasp(ring, pose, [], TABLE, suction, _tcp(pose[:3, 3] + [0, 0, 0.0075]), 0.0)
    assert hole.outcome == "drop"
    assert hole.seal is not None and not hole.seal.sealed
    assert hole.seal.reason in ("hole", "no_surface")
    box = _box((0.06, 0.04, 0.03))
    bpose = make_pose(translation=[0.0, 0.0, 0.015])
    held = validate_grasp(box, bpose, [], TABLE, suction, _tcp(bpose[:3, 3] + [0, 0, 0.015]), 0.0)
    assert held.outcome == "held", held.reason
    assert held.seal is not None and held.seal.sealed


def test_suction_over_an_edge_does_not_seal() -> None:
    box = _box((0.06, 0.04, 0.03))
    pose = make_pose(translation=[0.0, 0.0, 0.015])
    tcp = _tcp(pose[:3, 3] + [0.03, 0.0, 0.015])  # cup centred on the +x edge of the top face
    res = validate_grasp(box, pose, [], TABLE, GripperSpec.preset("suction"), tcp, 0.0)
    assert res.outcome != "held"
    assert res.seal is not None and res.seal.reason in ("edge", "hole")


def test_heavy_part_on_weak_vacuum_is_dropped() -> None:
    heavy = _box((0.06, 0.04, 0.03), mass=6.0)  # 59 N of weight against a 34 N cup
    pose = make_pose(translation=[0.0, 0.0, 0.015])
    res = validate_grasp(heavy, pose, [], TABLE, GripperSpec.preset("suction"), _tcp(pose[:3, 3] + [0, 0, 0.015]), 0.0)
    assert res.outcome == "drop"
    assert "vacuum let go" in res.reason


def test_ring_gripped_across_and_into_its_hole() -> None:
    ring = _ring()
    pose = make_pose(translation=[0.0, 0.0, 0.0075])
    assert len(collision_pieces(ring)) > 4  # non-convex: decomposed, the hole stays open
    tcp = _tcp(pose[:3, 3] + [0.0, 0.0, 0.0065])  # fingertips 1 mm above the table
    res = validate_grasp(ring, pose, [], TABLE, GripperSpec.preset("2f85"), tcp, 0.075)
    assert res.outcome == "held", res.reason
    # one 20 x 27 mm finger driven into the 36 mm hole to pinch the wall hits the far side of the wall
    tcp = _tcp(pose[:3, 3] + [0.024, 0.0, 0.0065])
    res = validate_grasp(ring, pose, [], TABLE, GripperSpec.preset("2f85"), tcp, 0.04)
    assert res.outcome == "collision" and res.collision_with.startswith("target")


def test_fingertips_driven_into_the_table_collide() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    tcp = _tcp(pose[:3, 3] - [0.0, 0.0, 0.015])  # tips 5 mm below the table top
    res = validate_grasp(cube, pose, [], TABLE, GripperSpec.preset("2f85"), tcp, 0.06)
    assert res.outcome == "collision"
    assert "table" in res.collision_with


def test_finger_landing_on_a_neighbour_collides() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    # a second cube right where the +x finger comes down
    nb_pose = make_pose(translation=[0.058, 0.0, 0.02])
    res = validate_grasp(cube, pose, [(cube, nb_pose)], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.07)
    assert res.outcome == "collision"
    assert res.collision_with.startswith("nb0")


def test_closing_on_air_misses() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    tcp = _tcp(pose[:3, 3] + [0.0, 0.0, 0.06])  # 4 cm above the cube
    res = validate_grasp(cube, pose, [], TABLE, GripperSpec.preset("2f85"), tcp, 0.06)
    assert res.outcome == "missed"


def test_deterministic() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(rotation_from_rotvec([0.0, 0.0, 0.3]), [0.0, 0.0, 0.02])
    tcp = _tcp(pose[:3, 3] + [0.003, 0.0, 0.0], closing=pose[:3, 0])
    nb = [(cube, make_pose(translation=[0.0, 0.09, 0.02]))]
    a = validate_grasp(cube, pose, nb, TABLE, GripperSpec.preset("2f85"), tcp, 0.06)
    b = validate_grasp(cube, pose, nb, TABLE, GripperSpec.preset("2f85"), tcp, 0.06)
    assert a.as_dict() == b.as_dict()
    assert np.array_equal(a.tcp_from_object, b.tcp_from_object)


def test_floor_added_when_no_static_geometry() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.3, -0.2, 0.82])  # on some table the caller did not describe
    res = validate_grasp(cube, pose, [], [], GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.06)
    assert res.outcome == "held", res.reason


def test_bad_inputs_raise_typed_errors() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    with pytest.raises(InputError, match="opening_m"):
        validate_grasp(cube, pose, [], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.2)
    bad = pose.copy()
    bad[:3, :3] *= 2.0
    with pytest.raises(InputError, match="world_from_object"):
        validate_grasp(cube, bad, [], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.06)
    with pytest.raises(InputError):
        GripperSpec(kind="magnet")
    with pytest.raises(InputError):
        GripperSpec.preset("robotiq-9000")


def test_gripper_spec_from_duck_typed_gripper() -> None:
    class FakeGripper:
        kind = "parallel"
        name = "wide"
        stroke_m = 0.14
        max_force_n = 125.0

    spec = GripperSpec.from_gripper(FakeGripper())
    assert spec.stroke_m == 0.14 and spec.grip_force_n == 125.0 and spec.kind == "parallel"

    class FakeCup:
        kind = "suction"
        cup_diameter_m = 0.04

    cup = GripperSpec.from_gripper(FakeCup(), vacuum_kpa=70.0)
    assert cup.kind == "suction" and cup.cup_diameter_m == 0.04
    assert cup.vacuum_force_n == pytest.approx(70e3 * np.pi * 0.02**2 * 0.8)


def test_options_are_respected() -> None:
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    opts = PhysicsOptions(lift_m=0.05, move_m=0.0, hold_s=0.1)
    res = validate_grasp(cube, pose, [], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.06, opts)
    assert res.lift_m == pytest.approx(0.05, abs=5e-3)


def test_a_far_neighbour_still_carries_a_simulated_part_resting_on_it() -> None:
    """A plate lying on a small block 0.3 m from the target: the plate comes within `neighbour_radius_m` (simulated),
    the block does not (fixed where it is). Left out, the block let the plate fall through it onto the table,
    8 mm into the block's volume at the end, and the next pick started from that overlap (seed 500 scene 45: a
    plate leaning on a far ring fell flat into it; on the ring's pick MuJoCo threw the ring 5 cm clear of the
    jaws, 'missed')."""
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    block = _box((0.02, 0.02, 0.02), name="block")
    plate = _box((0.2, 0.2, 0.01), mass=0.2, name="plate")
    block_pose = make_pose(translation=[0.3, 0.0, 0.01])
    plate_pose = make_pose(translation=[0.3, 0.0, 0.025])
    res = validate_grasp(
        cube, pose, [(block, block_pose), (plate, plate_pose)], TABLE, GripperSpec.preset("2f85"),
        _tcp(pose[:3, 3]), 0.06,
    )  # fmt: skip
    assert res.outcome == "held", res.reason
    np.testing.assert_allclose(res.world_from_neighbours_final[0], block_pose)  # fixed: not simulated
    assert res.world_from_neighbours_final[1][2, 3] == pytest.approx(0.025, abs=1e-3)  # still on the block


def test_final_poses_are_where_the_parts_came_to_rest() -> None:
    """A failed pick that lifted its part: the jaws open at lift height and the part falls. The run goes on until
    it lies still, so the next pick starts from a part at rest, not one frozen in mid-fall (seed 0 scene 74: a bar
    knocked on pick 3 was still tipping over, 0.3 m/s, when that run ended; pick 4 planned a leaned grasp on it,
    and it fell flat before the jaws closed: 'missed')."""
    cube = _box((0.04, 0.04, 0.04))
    pose = make_pose(translation=[0.0, 0.0, 0.02])
    opts = PhysicsOptions(slip_tolerance_m=1e-9, release_s=0.05)  # any motion is a slip; a short release
    res = validate_grasp(cube, pose, [], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.06, opts)
    assert res.outcome == "slip"
    assert res.world_from_object_final[2, 3] == pytest.approx(0.02, abs=2e-3)  # back on the table
    unrested = replace(opts, rest_s=0.0)
    res = validate_grasp(cube, pose, [], TABLE, GripperSpec.preset("2f85"), _tcp(pose[:3, 3]), 0.06, unrested)
    assert res.world_from_object_final[2, 3] > 0.05  # without it, frozen in mid-fall
