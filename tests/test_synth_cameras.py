"""Camera presets and poses: intrinsics scaling, look-at geometry (property tests), sampling ranges."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.errors import InputError
from normpos_grasp.sim.cameras import (
    INTRINSICS,
    CameraOptions,
    camera_intrinsics,
    camera_pose,
    parse_resolution,
    sample_camera,
)
from normpos_grasp.validation import check_pose


@settings(max_examples=60, deadline=None)
@given(
    dist=st.floats(0.2, 3.0),
    tilt=st.floats(0.0, 80.0),
    az=st.floats(-360.0, 360.0),
    roll=st.floats(-30.0, 30.0),
    tx=st.floats(-0.5, 0.5),
    ty=st.floats(-0.5, 0.5),
)
def test_camera_pose_looks_at_the_target_with_the_tilt(
    dist: float, tilt: float, az: float, roll: float, tx: float, ty: float
) -> None:
    target = np.array([tx, ty, 0.02])
    pose = check_pose(camera_pose(target, dist, tilt, az, roll))
    eye, forward = pose[:3, 3], pose[:3, 2]
    assert np.linalg.norm(eye - target) == pytest.approx(dist, rel=1e-9)
    np.testing.assert_allclose(forward, (target - eye) / dist, atol=1e-9)
    assert np.degrees(np.arccos(np.clip(-forward[2], -1, 1))) == pytest.approx(tilt, abs=1e-6)
    assert eye[2] > target[2]  # above the table
    # image "down" (camera +y) points towards the camera's side of the scene (no upside-down views)
    if tilt > 1.0 and abs(roll) < 30.0:
        horizontal_towards_camera = np.array([np.cos(np.radians(az)), np.sin(np.radians(az)), 0.0])
        assert pose[:3, 1] @ horizontal_towards_camera > 0


def test_intrinsics_presets_scale_with_resolution() -> None:
    for name, p in INTRINSICS.items():
        native = camera_intrinsics(name)
        assert (native.width, native.height) == (p.width, p.height) and native.fx == p.fx
        half = camera_intrinsics(name, (p.width // 2, p.height // 2))
        assert half.fx == pytest.approx(p.fx / 2)
        # same horizontal field of view
        assert np.arctan2(half.width / 2, half.fx) == pytest.approx(np.arctan2(p.width / 2, p.fx), rel=1e-3)
        assert native.world_from_camera is None and not native.has_distortion
    with pytest.raises(InputError, match="unknown sensor"):
        camera_intrinsics("kinect")
    assert parse_resolution("1280x720") == (1280, 720)
    with pytest.raises(InputError, match="640x480"):
        parse_resolution("640*480")


def test_sample_camera_respects_the_ranges() -> None:
    opts = CameraOptions(distance_m=(0.5, 0.6), tilt_deg=(10.0, 20.0), target_jitter_m=0.0, roll_deg=(0.0, 0.0))
    rng = np.random.default_rng(0)
    target = np.array([0.0, 0.0, 0.01])
    for _ in range(20):
        cam = sample_camera(opts, target, rng)
        pose = cam.require_world_from_camera()
        assert 0.5 <= np.linalg.norm(pose[:3, 3] - target) <= 0.6
        assert 10.0 - 1e-6 <= np.degrees(np.arccos(-pose[2, 2])) <= 20.0 + 1e-6
        assert (cam.width, cam.height) == (640, 480)
    with pytest.raises(InputError, match="tilt"):
        CameraOptions(tilt_deg=(10.0, 95.0))
