"""Projection / back-projection round trips (Eq. 1-5), serialisation and BOP camera entries."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.camera import Camera
from normpos_grasp.errors import InputError
from normpos_grasp.geometry import make_pose, random_rotation

K = np.array([[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]])


@settings(max_examples=60)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_project_backproject_round_trip(seed: int, distorted: bool) -> None:
    rng = np.random.default_rng(seed)
    dist = np.array([0.08, -0.15, 0.001, -0.0008, 0.03]) if distorted else np.zeros(5)
    cam = Camera(K, 640, 480, dist)
    pts = np.column_stack([rng.uniform(-0.25, 0.25, 40), rng.uniform(-0.2, 0.2, 40), rng.uniform(0.4, 2.0, 40)])
    px = cam.project(pts)
    back = cam.backproject(px, pts[:, 2])
    assert np.abs(back - pts).max() < 1e-7


def test_world_round_trip_and_json(tmp_path) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(3)
    wfc = make_pose(random_rotation(rng), [0.1, -0.2, 1.2])
    cam = Camera(K, 640, 480, world_from_camera=wfc)
    path = tmp_path / "camera.json"
    cam.save_json(path)
    loaded = Camera.load_json(path)
    assert np.allclose(loaded.K, cam.K)
    assert loaded.world_from_camera is not None
    assert np.allclose(loaded.world_from_camera, wfc)
    assert np.allclose(loaded.camera_from_world @ wfc, np.eye(4))


def test_bop_entry_round_trip() -> None:
    wfc = make_pose(random_rotation(np.random.default_rng(1)), [0.3, 0.1, 0.9])
    cam = Camera(K, 640, 480, depth_scale_m=0.0001, world_from_camera=wfc)
    entry = cam.to_bop()
    assert entry["depth_scale"] == pytest.approx(0.1)
    back = Camera.from_bop(entry, 640, 480)
    assert back.depth_scale_m == pytest.approx(0.0001)
    assert back.world_from_camera is not None
    assert np.allclose(back.world_from_camera, wfc, atol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"K": np.eye(3) * -1}, "fx, fy > 0"),
        ({"width": 0}, "image size"),
        ({"distortion": np.zeros(3)}, "coefficients"),
        ({"depth_scale_m": 0.0}, "depth_scale_m"),
        ({"world_from_camera": np.diag([1.0, 1.0, -1.0, 1.0])}, "reflection"),
    ],
)
def test_camera_rejects_bad_input(kwargs: dict, message: str) -> None:  # type: ignore[type-arg]
    args = {"K": K, "width": 640, "height": 480} | kwargs
    with pytest.raises(InputError, match=message):
        Camera(**args)


def test_camera_arrays_are_read_only() -> None:
    cam = Camera(K, 640, 480)
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0
