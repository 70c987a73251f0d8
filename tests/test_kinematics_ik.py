"""Analytic IK round trips (hypothesis), limits/branches, failure reasons, labels, Jacobian vs finite
differences, singularity measures, and factory calibration (FK and Newton-refined IK)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.errors import InputError, NoIKSolution, RobotModelError
from normpos_grasp.kinematics import ROBOT_NAMES, DHCalibration, DHChain, IKOptions, Robot, ur_params
from normpos_grasp.kinematics.robot import build_pinocchio_model

ROBOTS = {name: Robot.load(name) for name in ROBOT_NAMES}
angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
configs = st.tuples(angles, angles, angles, angles, angles, angles)


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(ROBOT_NAMES), q=configs)
def test_ik_round_trip_finds_the_start_configuration(name: str, q: tuple[float, ...]) -> None:
    robot = ROBOTS[name]
    qq = np.array(q)
    target = robot.fk(qq)
    sols = robot.ik(target, q_near=qq)
    assert sols.shape[0] >= 1 and sols.shape[1] == 6
    assert robot.within_limits(sols).all()
    np.testing.assert_allclose(robot.fk_batch(sols), np.broadcast_to(target, (len(sols), 4, 4)), atol=1e-9)
    # the nearest solution is the start configuration itself, away from singularities (at one, joints are only
    # determined to ~sqrt(eps) or, for the wrist, not at all)
    sd = robot.singularity_distance(qq)
    if min(sd.wrist, sd.elbow, sd.shoulder_m) > 1e-3:
        np.testing.assert_allclose(sols[0], qq, atol=1e-7)
    dist = np.linalg.norm(sols - qq, axis=1)
    assert np.all(np.diff(dist) >= -1e-12)


def test_branches_and_nearest_only() -> None:
    robot = ROBOTS["ur5e"]
    q = np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.2])
    target = robot.fk(q)
    every = robot.ik(target, q)
    nearest = robot.ik(target, q, IKOptions(all_branches=False))
    principal = robot.ik_batch(target[None])[1].sum()
    assert nearest.shape[0] == principal == 8
    assert every.shape[0] == 8 * 2**5  # five +-2 pi joints double, the +-pi elbow does not
    assert len({tuple(np.round(s, 9)) for s in every}) == every.shape[0]
    ur3e = ROBOTS["ur3e"]  # unlimited wrist 3: one copy, nearest to q_near
    sols = ur3e.ik(ur3e.fk(q), q_near=q + np.array([0, 0, 0, 0, 0, 4 * math.pi]))
    assert sols[0][5] == pytest.approx(q[5] + 4 * math.pi)


def test_batch_matches_single() -> None:
    robot = ROBOTS["ur10e"]
    rng = np.random.default_rng(3)
    qs = rng.uniform(-math.pi, math.pi, (200, 6))
    poses = robot.fk_batch(qs)
    q8, valid = robot.ik_batch(poses)
    assert valid.any(axis=1).all()
    err = np.abs(robot.fk_batch(np.nan_to_num(q8.reshape(-1, 6))).reshape(200, 8, 4, 4) - poses[:, None]).max((2, 3))
    assert (err[valid] < 1e-9).all()
    for i in range(0, 200, 40):
        single = robot.ik(poses[i], options=IKOptions(all_branches=False))
        assert single.shape[0] == valid[i].sum()


def test_labels_cover_all_eight_configurations() -> None:
    robot = ROBOTS["ur5e"]
    q = np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.2])
    q8, valid = robot.ik_batch(robot.fk(q)[None])
    assert valid.all()
    labels = [robot.ik_labels(s) for s in q8[0]]
    assert len({str(lab) for lab in labels}) == 8
    home = robot.ik_labels([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])
    assert home.wrist == "noflip"
    # solutions that share the wrist branch bit share the wrist label, likewise shoulder
    for i in range(8):
        assert labels[i].wrist == labels[i ^ 1].wrist
        assert labels[i].shoulder == labels[i ^ 2].shoulder


def test_unreachable_reasons() -> None:
    robot = ROBOTS["ur5e"]
    far = np.eye(4)
    far[:3, 3] = (2.0, 0.0, 0.3)
    assert robot.ik(far).shape == (0, 6)
    with pytest.raises(NoIKSolution) as exc:
        robot.ik_or_raise(far)
    assert exc.value.reason == "out_of_reach"
    # wrist centre inside the d4 cylinder around the base axis
    inner = np.eye(4)
    inner[:3, 3] = (0.0, 0.0, 0.3 + robot.params.d[5])
    with pytest.raises(NoIKSolution, match="d4") as exc:
        robot.ik_or_raise(inner)
    assert exc.value.reason == "out_of_reach"
    # wrist singularity: q5 = 0 (joints 4 and 6 aligned) is still solved by ik(), refused by ik_or_raise
    q = np.array([0.2, -1.3, 1.5, -1.0, 0.0, 0.3])
    sols = robot.ik(robot.fk(q), q)
    assert sols.shape[0] > 0
    np.testing.assert_allclose(robot.fk(sols[0]), robot.fk(q), atol=1e-9)
    regular = robot.manipulability(np.array([0.2, -1.3, 1.5, -1.0, 1.2, 0.3]))
    assert regular > 1e-3  # m^3: the scale of the measure at a regular pose of a UR5e
    assert robot.manipulability(q) < 1e-9 * regular  # rounding only, at any BLAS build
    allowed = robot.ik_or_raise(robot.fk(q), q)  # other branches are regular: they remain
    assert np.all(np.abs(np.sin(allowed[:, 4])) >= IKOptions().wrist_singularity_tol)
    # with the shoulder pan limited to +-0.5 rad only the singular branch is left
    params = dataclasses.replace(ur_params("ur5e"), position_limit=(0.5, 6.3, 3.15, 6.3, 6.3, 6.3))
    narrow = Robot(params)
    assert np.all(np.abs(np.sin(narrow.ik(robot.fk(q), q)[:, 4])) < 1e-9)
    with pytest.raises(NoIKSolution) as exc:
        narrow.ik_or_raise(robot.fk(q), q)
    assert exc.value.reason == "wrist_singularity"
    # joint limits: a copy of the UR5e whose shoulder pan is limited to +-0.1 rad
    params = dataclasses.replace(ur_params("ur5e"), position_limit=(0.1, 6.3, 3.15, 6.3, 6.3, 6.3))
    narrow = Robot(params)
    q = np.array([1.5, -1.2, 1.4, -1.7, -1.5, 0.2])
    with pytest.raises(NoIKSolution) as exc:
        narrow.ik_or_raise(robot.fk(q))
    assert exc.value.reason == "joint_limits"
    assert narrow.ik(robot.fk(q)).shape == (0, 6)


def test_bad_target_is_an_input_error() -> None:
    robot = ROBOTS["ur5e"]
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(InputError):
        robot.ik(bad)
    with pytest.raises(InputError):
        robot.fk([0.0] * 5)


@pytest.mark.parametrize("name", ["ur5e", "ur20"])
def test_jacobian_matches_finite_differences(name: str) -> None:
    robot = ROBOTS[name]
    rng = np.random.default_rng(11)
    eps = 1e-6
    for q in rng.uniform(-math.pi, math.pi, (5, 6)):
        jac = robot.jacobian(q)
        pose = robot.fk(q)
        for j in range(6):
            dq = np.zeros(6)
            dq[j] = eps
            plus, minus = robot.fk(q + dq), robot.fk(q - dq)
            np.testing.assert_allclose(jac[:3, j], (plus[:3, 3] - minus[:3, 3]) / (2 * eps), atol=1e-7)
            d_rot = (plus[:3, :3] - minus[:3, :3]) / (2 * eps) @ pose[:3, :3].T  # skew(w)
            np.testing.assert_allclose(jac[3:, j], [d_rot[2, 1], d_rot[0, 2], d_rot[1, 0]], atol=1e-7)


def test_singularity_distance() -> None:
    robot = ROBOTS["ur5e"]
    q = np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.2])
    sd = robot.singularity_distance(q)
    assert sd.wrist == pytest.approx(abs(math.sin(q[4])))
    assert sd.elbow == pytest.approx(abs(math.sin(q[2])))
    assert sd.shoulder_m > 0.1 and sd.min_singular_value > 0
    stretched = q.copy()
    stretched[2] = 0.0
    assert robot.singularity_distance(stretched).min_singular_value < 1e-9
    assert robot.manipulability(q) > robot.manipulability(stretched)


CONF = """# calibration.conf of a UR5e (synthetic deltas of realistic size)
[mounting]
delta_theta = [ 1.2e-05, 0.31, -0.62, 0.31, 2.1e-05, -1.4e-05]
delta_a = [ 3.1e-05, 0.00042, 0.0011, 1.1e-05, 2.2e-05, 0]
delta_d = [ 0.00021, -14.5, 23.1, -8.6, 4.2e-05, -1.8e-05]
delta_alpha = [ -1.1e-05, 0.0009, 0.0012, -0.0003, 6e-05, 0]
"""


def _consistent_conf() -> DHCalibration:
    """Large compensating offsets as in real files are unsafe to invent; use mm-scale deltas instead."""
    rng = np.random.default_rng(5)
    return DHCalibration(*(tuple(float(v) for v in rng.normal(0, s, 6)) for s in (2e-3, 1e-3, 1e-3, 2e-3)))


def test_calibration_file_parsing(tmp_path: Path) -> None:
    cal = DHCalibration.from_text(CONF)
    assert cal.delta_d[1] == -14.5 and cal.delta_theta[2] == -0.62
    path = tmp_path / "calibration.conf"
    path.write_text(_consistent_conf().to_text())
    assert DHCalibration.from_conf(path) == _consistent_conf()
    with pytest.raises(RobotModelError, match="6 finite numbers"):
        DHCalibration.from_text("delta_a = [1, 2]")
    with pytest.raises(RobotModelError, match="no delta"):
        DHCalibration.from_text("[mounting]\n")


def test_calibrated_fk_and_ik(tmp_path: Path) -> None:
    path = tmp_path / "calibration.conf"
    path.write_text(_consistent_conf().to_text())
    robot = Robot.load("ur5e", calibration=path)
    nominal = ROBOTS["ur5e"]
    q = np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.2])
    assert robot.calibrated
    shift = np.abs(robot.fk(q)[:3, 3] - nominal.fk(q)[:3, 3]).max()
    assert 1e-4 < shift < 0.05
    np.testing.assert_allclose(robot.fk(q), robot.chain.forward_kinematics(q), atol=1e-12)
    # the calibrated MJCF built at run time agrees too
    model = robot.mujoco_model()
    data = mujoco.MjData(model)
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    np.testing.assert_allclose(data.site("flange").xpos, robot.fk(q)[:3, 3], atol=1e-9)
    rng = np.random.default_rng(9)
    for qq in rng.uniform(-math.pi, math.pi, (20, 6)):
        if abs(math.sin(qq[4])) < 1e-2:
            continue
        target = robot.fk(qq)
        sols = robot.ik(target, qq)
        assert sols.shape[0] >= 1
        np.testing.assert_allclose(sols[0], qq, atol=1e-8)
        np.testing.assert_allclose(robot.fk_batch(sols), np.broadcast_to(target, (len(sols), 4, 4)), atol=1e-9)
    with pytest.raises(RobotModelError):
        robot.ik_batch(robot.fk(q)[None])


def test_pinocchio_model_from_chain_matches_dh() -> None:
    params = ur_params("ur16e")
    chain = DHChain.nominal(params, _consistent_conf())
    model = build_pinocchio_model(params, chain)
    assert [model.names[i] for i in range(1, 7)][0] == "shoulder_pan_joint"
    assert model.upperPositionLimit[2] == pytest.approx(math.pi)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_round_trip_on_singular_and_boundary_configurations(name: str) -> None:
    """Joint values at 0, +-pi/2, +-pi and tiny angles put the arm at (double) singularities: stretched elbow,
    aligned wrist, wrist centre on the shoulder plane; every such pose must still be solved to 1e-9."""
    robot = ROBOTS[name]
    rng = np.random.default_rng(13)
    special = np.array([0.0, math.pi / 2, -math.pi / 2, math.pi, -math.pi, 1e-9, 1e-7, 1e-6, 0.25])
    for _ in range(150):
        q = rng.uniform(-math.pi, math.pi, 6)
        mask = rng.random(6) < 0.5
        q[mask] = rng.choice(special, int(mask.sum()))
        target = robot.fk(q)
        sols = robot.ik(target, q, IKOptions(all_branches=False))
        assert sols.shape[0] >= 1, q
        assert np.abs(robot.fk_batch(sols) - target).max() <= 1e-9, q


def _wrap(q: np.ndarray) -> np.ndarray:
    return q - 2 * math.pi * np.round(q / (2 * math.pi))


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_single_pose_path_equals_the_batched_path(name: str) -> None:
    """robot.ik (compiled one-pose path) against ik_batch + an independent numpy expansion to each joint's
    nearest in-limit copy, sorted by distance: same solutions, same order, to 1e-12 rad."""
    robot = ROBOTS[name]
    rng = np.random.default_rng(11)
    lower, upper = robot.joint_limits
    qs = rng.uniform(np.maximum(lower, -2 * math.pi), np.minimum(upper, 2 * math.pi), (300, 6))
    poses = robot.fk_batch(qs)
    q8, valid = robot.ik_batch(poses, q6_default=0.0)
    near_all = qs + rng.normal(0.0, 0.7, qs.shape)
    near_opts = IKOptions(all_branches=False)
    d4 = robot.params.d[3]
    compared = 0
    for i in range(len(qs)):
        principal = q8[i][valid[i]]
        shoulder = math.acos(min(1.0, d4 / np.hypot(*(poses[i, :2, 3] - robot.params.d[5] * poses[i, :2, 2]))))
        if shoulder < 1e-4 or (np.abs(np.sin(principal[:, [2, 4]])) < 1e-4).any():
            continue  # near a singularity the one-pose path Newton-polishes (differences up to ~1e-8 rad)
        near = near_all[i]
        q6 = robot.ik_batch(poses[i][None], q6_default=float(near[5]))[0][0][valid[i]]
        cand = np.stack([q6, q6 - np.copysign(2 * math.pi, q6)])  # (2, k, 6): principal and its other copy
        unlimited = ~np.isfinite(upper)
        turns = np.round((near[unlimited] - q6[:, unlimited]) / (2 * math.pi))
        cand[:, :, unlimited] = q6[:, unlimited] + 2 * math.pi * turns
        in_limits = np.abs(cand) <= upper
        dist = np.where(in_limits, np.abs(cand - near), np.inf)
        pick = np.take_along_axis(cand, np.argmin(dist, axis=0)[None], axis=0)[0]
        expected = pick[np.all(np.abs(pick) <= upper, axis=1)]
        expected = expected[np.argsort(((expected - near) ** 2).sum(axis=1), kind="stable")]
        single = robot.ik(poses[i], near, near_opts)
        assert single.shape == expected.shape
        np.testing.assert_allclose(single, expected, rtol=0, atol=1e-12)
        every = robot.ik(poses[i], near)  # every +-2 pi copy: the same principal solutions, nearest first
        assert every.shape[0] >= single.shape[0]
        np.testing.assert_allclose(every[0], single[0], rtol=0, atol=1e-12)
        got = {tuple(np.round(_wrap(s), 9)) for s in every}
        assert got == {tuple(np.round(_wrap(s), 9)) for s in expected}
        compared += 1
    assert compared > 250


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_compiled_one_pose_path_equals_the_python_path(name: str) -> None:
    """Same shapes and values (1e-12 rad) as Robot._ik_python on random, wrist-, elbow-singular and boundary
    poses, with and without q_near, nearest copies and every copy (singular poses fall back to the Python path)."""
    robot = ROBOTS[name]
    rng = np.random.default_rng(12)
    lower, upper = robot.joint_limits
    qs = rng.uniform(np.maximum(lower, -2 * math.pi), np.minimum(upper, 2 * math.pi), (120, 6))
    qs[:20, 4] = rng.choice([0.0, math.pi, 1e-6], 20)  # aligned wrist (and just beside it)
    qs[20:40, 2] = rng.choice([0.0, 2e-5], 20)  # stretched elbow
    poses = robot.fk_batch(qs)
    for i in range(len(qs)):
        for opts in (IKOptions(), IKOptions(all_branches=False)):
            for near in (qs[i] + rng.normal(0.0, 0.5, 6), None):
                fast = robot.ik(poses[i], near, opts)
                slow = robot._ik_python(poses[i], near, opts)
                assert fast.shape == slow.shape
                np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)
    far = np.eye(4)
    far[:3, 3] = (3.0, 0.0, 0.3)
    assert robot.ik(far).shape == (0, 6) == robot._ik_python(far, None, IKOptions()).shape


def test_one_pose_path_refuses_bad_input() -> None:
    robot = ROBOTS["ur5e"]
    target = robot.fk(np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.2]))
    sheared = target + np.diag([0.1, 0.0, 0.0, 0.0])
    for bad_pose in (np.full((4, 4), np.nan), target[:3], sheared):
        with pytest.raises(InputError):
            robot.ik(bad_pose)
    shifted = target.copy()
    shifted[3, 3] = 2.0  # last row not [0, 0, 0, 1]
    with pytest.raises(InputError):
        robot.ik(shifted)
    for bad_near in ([0.0] * 5, [0.0, 0.0, 0.0, 0.0, 0.0, math.inf]):
        with pytest.raises(InputError):
            robot.ik(target, bad_near)
    assert robot.ik(target.tolist(), [0.0] * 6).shape[0] > 0  # nested lists are accepted
