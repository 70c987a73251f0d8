"""Property tests of the rigid-body helpers: round trips, det R = +1, Kabsch recovery under noise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.errors import InputError
from normpos_grasp.geometry import (
    invert_pose,
    kabsch,
    make_pose,
    pose_from_ur,
    pose_to_ur,
    random_rotation,
    rotation_angle,
    rotation_from_rotvec,
    rotation_to_rotvec,
    transform_points,
)
from normpos_grasp.geometry.transforms import look_at
from normpos_grasp.validation import check_pose

seeds = st.integers(min_value=0, max_value=2**32 - 1)


@given(seeds)
def test_random_rotation_is_proper(seed: int) -> None:
    rot = random_rotation(np.random.default_rng(seed))
    assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)


@given(seeds)
def test_rotvec_round_trip(seed: int) -> None:
    rot = random_rotation(np.random.default_rng(seed))
    assert np.allclose(rotation_from_rotvec(rotation_to_rotvec(rot)), rot, atol=1e-9)


def test_rotvec_near_pi_is_stable() -> None:
    for axis in (np.array([1.0, 0, 0]), np.array([1.0, 1.0, 0]) / np.sqrt(2), np.array([0.3, -0.4, 0.866])):
        axis = axis / np.linalg.norm(axis)
        rot = rotation_from_rotvec(axis * (np.pi - 1e-9))
        assert np.allclose(rotation_from_rotvec(rotation_to_rotvec(rot)), rot, atol=1e-7)
        assert rotation_angle(rot) == pytest.approx(np.pi, abs=1e-7)


@given(seeds)
def test_pose_inverse_and_ur_vector_round_trip(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = make_pose(random_rotation(rng), rng.normal(size=3))
    assert np.allclose(invert_pose(pose) @ pose, np.eye(4), atol=1e-12)
    assert np.allclose(pose_from_ur(pose_to_ur(pose)), pose, atol=1e-9)


@settings(max_examples=50)
@given(seeds, st.integers(min_value=3, max_value=60), st.floats(min_value=0.0, max_value=0.002))
def test_kabsch_recovers_transform_of_noisy_points(seed: int, n: int, noise: float) -> None:
    rng = np.random.default_rng(seed)
    src = rng.uniform(-0.1, 0.1, size=(n, 3))
    truth = make_pose(random_rotation(rng), rng.uniform(-1, 1, size=3))
    dst = transform_points(truth, src) + rng.normal(scale=noise, size=(n, 3))
    spread = np.linalg.svd(src - src.mean(0), compute_uv=False)
    if spread[1] < 0.02:  # nearly collinear draws are ill-posed, not a failure of the solver
        return
    est = kabsch(src, dst)
    assert np.linalg.det(est[:3, :3]) == pytest.approx(1.0)
    # error bound: noise over spread, generously
    assert rotation_angle(est[:3, :3].T @ truth[:3, :3]) < 1e-9 + 20 * noise / spread[1]
    assert np.linalg.norm(est[:3, 3] - truth[:3, 3]) < 1e-9 + 20 * noise * (1 + 1 / spread[1])


def test_kabsch_never_reflects() -> None:
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    mirrored = src * [1, 1, -1]
    est = kabsch(src, mirrored)
    assert np.linalg.det(est[:3, :3]) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("src", "message"),
    [
        (np.zeros((2, 3)), "at least 3"),
        (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), "collinear"),
        (np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0.0]]), "NaN"),
    ],
)
def test_kabsch_rejects_degenerate_input(src: np.ndarray, message: str) -> None:
    with pytest.raises(InputError, match=message):
        kabsch(src, src)


def test_check_pose_rejects_reflection_and_bad_last_row() -> None:
    with pytest.raises(InputError, match="proper rotation"):
        check_pose(np.diag([1.0, 1.0, -1.0, 1.0]))
    bad = np.eye(4)
    bad[3, 0] = 1
    with pytest.raises(InputError, match="last row"):
        check_pose(bad)


def test_look_at_is_opencv_convention() -> None:
    wfc = look_at([0.0, -1.0, 1.0], [0.0, 0.0, 0.0])
    z = wfc[:3, 2]
    assert np.allclose(z, np.array([0, 1, -1]) / np.sqrt(2))
    assert wfc[2, 1] < 0  # image down points to world down
    assert np.linalg.det(wfc[:3, :3]) == pytest.approx(1.0)
    straight_down = look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    assert np.allclose(straight_down[:3, 2], [0, 0, -1])
