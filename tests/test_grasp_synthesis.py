"""Automatic grasp synthesis per shape, annotation expansion, batched analytic IK, RRT-Connect, timing."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.errors import PlanningError
from normpos_grasp.geometry import make_pose
from normpos_grasp.grasp import CandidateOptions, SynthesisOptions, expand_annotation, synthesize
from normpos_grasp.kinematics import Robot
from normpos_grasp.planning import ArmModel
from normpos_grasp.planning.rrt import MotionOptions, edge_free, plan_joint_motion
from normpos_grasp.planning.timing import time_parameterise
from normpos_grasp.records.template import GraspAnnotation, Symmetry, Template

OPTS = SynthesisOptions()


def _is_rotation(pose: np.ndarray) -> bool:
    r = pose[:3, :3]
    return bool(np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.linalg.det(r) > 0)


def test_box_parallel_pairs_and_face_suction() -> None:
    ext = np.array([0.06, 0.04, 0.03])
    t = Template("box", "box", trimesh.creation.box(ext), shape="box")
    grasps = synthesize(t)
    parallel = [g for g in grasps if g.scheme == "parallel"]
    suction = [g for g in grasps if g.scheme == "suction"]
    nominal = [g for g in parallel if "_t" not in g.id and "_s" not in g.id]
    assert len(nominal) == 12  # 3 closing axes x 2 approach axes x 2 sides
    # the 0.06 side is long enough to slide along: pinches across the other two axes come 3x; every pinch also
    # comes tilted by +-20 degrees about its closing axis
    n_slid = 2 * 2  # (closing, approach) = (y, z) or (z, y), two sides each: two off-centre slides each
    assert len(parallel) == (12 + n_slid * 2) * (1 + 2 * len(OPTS.tilt_angles_rad))
    for g in parallel:
        pose = g.object_from_tcp
        assert _is_rotation(pose)
        i = int(np.argmax(np.abs(pose[:3, 0])))
        assert abs(pose[i, 0]) == pytest.approx(1.0)  # jaws close along a box axis, tilted or not
        assert g.opening_m == pytest.approx(ext[i] + 2 * OPTS.clearance_m)
        assert t.mesh.contains([pose[:3, 3]])[0]  # TCP inside the part at grasp depth
    for g in nominal:
        i = int(np.argmax(np.abs(g.object_from_tcp[:3, 2])))
        assert abs(g.object_from_tcp[i, 2]) == pytest.approx(1.0)  # nominal: approach along a box axis
    tilted = [g for g in parallel if "_t" in g.id]
    for g in tilted:
        a = g.object_from_tcp[:3, 2]
        assert np.sort(np.abs(a))[-1] == pytest.approx(np.cos(OPTS.tilt_angles_rad[0]))
    # suction: faces at least cup-sized; the TCP lies on the face, approach into the part
    for g in suction:
        pose = g.object_from_tcp
        a = pose[:3, 2]
        j = int(np.argmax(np.abs(a)))
        assert abs(pose[j, 3]) == pytest.approx(ext[j] / 2)
        assert np.sign(pose[j, 3]) == -np.sign(a[j])
    assert len(suction) == 2 * 2 * 3  # 6 faces (all >= 30 mm), two roll angles each


def test_cylinder_sphere_plate_schemes() -> None:
    cyl = Template(
        "c",
        "c",
        trimesh.creation.cylinder(0.02, 0.07),
        shape="cylinder",
        symmetry=Symmetry(continuous=((np.array([0.0, 0.0, 1.0]), np.zeros(3)),)),
    )
    g = synthesize(cyl)
    side = [x for x in g if x.id.startswith("cyl_side_") and x.scheme == "parallel" and "_t" not in x.id]
    leaning = [x for x in g if x.id.startswith("cyl_side_") and "_t" in x.id]
    # tilted side grasps lean along the axis; the jaws still close across it
    assert leaning and all(abs(x.object_from_tcp[2, 0]) < 1e-9 and abs(x.object_from_tcp[2, 2]) > 0.3 for x in leaning)
    assert side and all(abs(x.object_from_tcp[2, 2]) < 1e-9 and abs(x.object_from_tcp[2, 0]) < 1e-9 for x in side)
    assert all(x.opening_m == pytest.approx(0.04 + 2 * OPTS.clearance_m) for x in side)
    assert any(x.id.startswith("cyl_cap_suction") for x in g)
    # without a declared symmetry the axis is found from the box extents
    cyl2 = Template("c", "c", trimesh.creation.cylinder(0.02, 0.07, sections=64), shape="cylinder")
    side2 = [
        x for x in synthesize(cyl2) if x.id.startswith("cyl_side_") and x.scheme == "parallel" and "_t" not in x.id
    ]
    assert side2 and all(abs(x.object_from_tcp[2, 2]) < 1e-6 for x in side2)
    sph = Template("s", "s", trimesh.creation.icosphere(3, 0.0225), shape="sphere")
    gs = synthesize(sph, ("parallel",))
    assert gs and all(x.opening_m == pytest.approx(0.045 + 2 * OPTS.clearance_m, abs=1e-3) for x in gs)
    plate = Template("p", "p", trimesh.creation.box((0.08, 0.06, 0.008)), shape="plate")
    gp = synthesize(plate)
    pinches = [x for x in gp if x.id.startswith("plate_edge")]
    assert pinches and all(abs(x.object_from_tcp[2, 0]) == pytest.approx(1.0) for x in pinches)
    assert all(x.opening_m == pytest.approx(0.008 + 2 * OPTS.clearance_m) for x in pinches)
    across = [x for x in gp if x.id.startswith("plate_across")]  # from the face, closing across width / length
    nominal = [x for x in across if "_s" not in x.id and "_t" not in x.id]
    assert len(nominal) == 4 and all(abs(x.object_from_tcp[2, 2]) == pytest.approx(1.0) for x in nominal)
    assert sorted(round(x.opening_m, 4) for x in nominal) == pytest.approx([0.08, 0.08, 0.1, 0.1])
    assert all(abs(x.object_from_tcp[2, 2]) == pytest.approx(1.0) for x in across)  # never tilted: too thin
    # slid copies a quarter of the side along the jaw width off centre (80 mm side: 20 mm, 60 mm side: 15 mm)
    slid = [x for x in across if x.id.endswith(("_s1", "_s2"))]
    offsets = {round(float(np.linalg.norm(x.object_from_tcp[:2, 3])), 6) for x in slid}
    assert slid and offsets == {0.015, 0.02}
    assert any(x.scheme == "suction" and x.object_from_tcp[2, 2] < -0.99 for x in gp)


@settings(max_examples=4, deadline=None)
@given(mu=st.floats(0.2, 0.8), seed=st.integers(0, 100))
def test_antipodal_pairs_respect_the_friction_cone(mu: float, seed: int) -> None:
    mesh = trimesh.creation.annulus(0.018, 0.03, 0.015)
    t = Template("ring", "ring", mesh, shape="ring")
    opts = SynthesisOptions(friction_coef=mu, seed=seed, antipodal_samples=80)
    grasps = [g for g in synthesize(t, ("parallel",), opts) if g.id.startswith("antipodal")]
    assert grasps
    cone = np.arctan(mu)
    for g in grasps[::4]:
        pose = g.object_from_tcp
        centre, axis = pose[:3, 3], pose[:3, 0]
        half = (g.opening_m - 2 * opts.clearance_m) / 2
        for sign in (-1, 1):
            p = centre + sign * half * axis
            _, _, tri = trimesh.proximity.closest_point(mesh, [p])
            n = mesh.face_normals[tri[0]]
            # the contact normal points outwards along +-axis within the cone
            assert np.arccos(np.clip(np.dot(n, sign * axis), -1, 1)) <= cone + 1e-6
    again = [g for g in synthesize(t, ("parallel",), opts) if g.id.startswith("antipodal")]
    assert [g.id for g in again] == [g.id for g in grasps]  # seeded: reproducible


def test_annotation_free_axis_and_tilt_expansion() -> None:
    base = make_pose(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.03])
    g = GraspAnnotation("top", "parallel", base, opening_m=0.05, free_axis=np.array([0.0, 0.0, 1.0]), tilt_cone_rad=0.2)
    out = expand_annotation(g, CandidateOptions(free_axis_steps=6, tilt_steps=4))
    assert len(out) == 6 * 5
    for _gid, pose in out:
        assert _is_rotation(pose)
        np.testing.assert_allclose(pose[:3, 3], [0.0, 0.0, 0.03], atol=1e-12)  # rotation about the part's axis
        tilt = np.arccos(np.clip(-pose[2, 2], -1, 1))
        assert tilt == pytest.approx(0.0, abs=1e-9) or tilt == pytest.approx(0.2, abs=1e-9)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6), st.sampled_from(["ur3e", "ur5e", "ur10e", "ur20"]))
def test_batched_ik_round_trips_against_pinocchio_fk(q: list[float], model: str) -> None:
    arm = ArmModel.from_name(model, make_pose(None, [0.1, -0.2, 0.3]))
    robot = Robot.load(model)
    pose = arm.world_from_base @ robot.fk(np.array(q))
    qs, exists, _ = arm.ik_reasons(pose[None])
    if not exists.any():  # exactly singular draws
        return
    for k in np.flatnonzero(exists[0]):
        np.testing.assert_allclose(arm.world_from_base @ robot.fk(qs[0, k]), pose, atol=1e-7)
    if abs(np.sin(q[4])) > 1e-3 and abs(np.sin(q[2])) > 1e-3:  # away from wrist / elbow singularities
        d = np.abs((qs[0] - np.array(q) + np.pi) % (2 * np.pi) - np.pi).max(axis=1)
        assert d[exists[0]].min() < 1e-6  # the original configuration is among the branches


def test_rrt_connect_goes_around_an_obstacle() -> None:
    lower, upper = np.full(6, -np.pi), np.full(6, np.pi)

    def free(q: np.ndarray) -> bool:  # a slab in (q0, q1) blocking the straight line
        return not (-0.3 < q[0] < 0.3 and q[1] < 1.5)

    start, goal = np.array([-1.0, 0, 0, 0, 0, 0]), np.array([1.0, 0, 0, 0, 0, 0])
    opts = MotionOptions()
    assert not edge_free(start, goal, free, opts.resolution_rad)
    path = plan_joint_motion(start, goal, free, lower, upper, opts)
    assert np.allclose(path[0], start) and np.allclose(path[-1], goal)
    assert all(edge_free(a, b, free, opts.resolution_rad) for a, b in zip(path[:-1], path[1:], strict=True))
    with pytest.raises(PlanningError, match="goal"):
        plan_joint_motion(start, np.zeros(6), free, lower, upper, opts)


def test_time_parameterisation_respects_caps() -> None:
    vmax, amax = np.full(6, 1.0), np.full(6, 2.0)
    line = np.linspace([0, 0, 0, 0, 0, 0], [1.0, -0.5, 0.2, 0, 0, 0.1], 30)
    jump = np.array([[1.0, -0.5, 0.2, 0, 0, 0.1], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    traj = time_parameterise([line, jump], vmax, amax)
    dt = np.diff(traj.t)
    vel = np.diff(traj.q, axis=0) / dt[:, None]
    assert np.all(np.abs(vel) <= vmax * 1.02)
    acc = np.diff(vel, axis=0) / dt[1:, None]
    assert np.all(np.abs(acc) <= amax * 1.1)
    np.testing.assert_allclose(traj.q[0], line[0])
    np.testing.assert_allclose(traj.q[-1], jump[-1])
    assert traj.duration_s >= 2 * 1.0 / 1.0  # at least two 1-rad moves at 1 rad/s


def test_cut_extent_from_one_outline_equals_the_hull_per_height() -> None:
    """vertical_prism_grasps computes a cut's hull once for its three tip heights: the extents equal one hull each."""
    from normpos_grasp.grasp.candidates import _cut_outline, _extent_above

    rng = np.random.default_rng(11)
    cuts = [rng.normal(scale=0.02, size=(n, 2)) for n in (3, 5, 12, 40)]
    cuts.append(np.column_stack([np.linspace(0, 0.03, 6), np.linspace(0, 0.01, 6)]))  # collinear: no hull
    cuts.append(np.array([[0.0, 0.0], [0.01, 0.02]]))  # two points
    for cut in cuts:
        outline = _cut_outline(cut)
        lo_z, hi_z = float(cut[:, 1].min()), float(cut[:, 1].max())
        for z in np.linspace(lo_z - 0.01, hi_z + 0.01, 9):
            assert _extent_above(cut, float(z), outline) == _extent_above(cut, float(z))
    wide = np.array([[-0.02, 0.0], [0.02, 0.0], [0.0, 0.04]])  # a triangle, apex up
    lo, hi = _extent_above(wide, 0.02, _cut_outline(wide))
    assert lo == pytest.approx(-0.01) and hi == pytest.approx(0.01)  # the hull's edges cut at half height
