"""Depth bias from the support plane: a known synthetic bias is recovered; a wrong frame is reported."""

from __future__ import annotations

import numpy as np
import pytest

from normpos_grasp.errors import InputError
from normpos_grasp.measure.depth_bias import (
    DepthBiasOptions,
    correct_depth,
    estimate_depth_bias,
    plane_in_camera,
)
from normpos_grasp.sim.cameras import CameraOptions
from normpos_grasp.sim.dataset import SyntheticFrame, generate_frame
from normpos_grasp.sim.scene import SceneOptions
from normpos_grasp.sim.sensor import sensor_preset


def _bin_floor_plane(sf: SyntheticFrame) -> np.ndarray:
    """World plane (z up) of the bin floor's top face, from the scene's static geometry."""
    (_, pose, size) = next(b for b in sf.layout.static_boxes if b[0] == "bin_floor")
    top = float(pose[2, 3] + size[2] / 2)
    return np.array([0.0, 0.0, 1.0, -top])


@pytest.fixture(scope="module", params=[0.0, 0.007])
def frame_and_bias(request: pytest.FixtureRequest) -> tuple[SyntheticFrame, float]:
    bias = float(request.param)
    sf = generate_frame(
        SceneOptions(count=3, seed=21),
        sensor_preset("d435", depth_bias_m=bias),
        CameraOptions(distance_m=(0.6, 0.8)),
        seed=5,
        backend="raycast",
    )
    return sf, bias


def test_known_bias_recovered_within_1mm(frame_and_bias: tuple[SyntheticFrame, float]) -> None:
    sf, bias = frame_and_bias
    cam = sf.frame.camera
    plane = plane_in_camera(_bin_floor_plane(sf), cam.require_world_from_camera())
    est = estimate_depth_bias(cam, sf.frame.depth_m, plane)
    assert abs(est.bias_m - bias) < 0.001, est
    assert est.ok and est.tilt_deg < 1.0
    # corrected depth gives no bias; holes stay holes
    fixed = correct_depth(sf.frame.depth_m, est.corrected)
    assert np.array_equal(fixed > 0, sf.frame.depth_m > 0)
    again = estimate_depth_bias(cam, fixed, plane)
    assert abs(again.bias_m) < 0.001


def test_frame_that_looks_wrong_is_reported(frame_and_bias: tuple[SyntheticFrame, float]) -> None:
    sf, _ = frame_and_bias
    cam = sf.frame.camera
    plane = plane_in_camera(_bin_floor_plane(sf), cam.require_world_from_camera())
    far = estimate_depth_bias(cam, sf.frame.depth_m + 0.045, plane)  # 4.5 cm: beyond max_bias_m
    assert not far.ok and any("exceeds" in w for w in far.warnings)
    assert far.corrected == 0.0
    holes = sf.frame.depth_m.copy()
    holes[:, : int(0.8 * cam.width)] = 0.0
    sparse = estimate_depth_bias(cam, holes, plane)
    assert not sparse.ok and any("valid depth" in w for w in sparse.warnings)
    nowhere = estimate_depth_bias(cam, sf.frame.depth_m, plane_in_camera(np.array([0, 0, 1.0, 0.5]), np.eye(4)))
    assert not nowhere.ok and not np.isfinite(nowhere.bias_m)


def test_options_validated() -> None:
    with pytest.raises(InputError):
        DepthBiasOptions(stride=0)


@pytest.mark.parametrize("bias", [0.0, 0.007])
def test_pipeline_check_from_the_cell(bias: float) -> None:
    """`check_frame_depth`: the cell's bin floor gives the plane; the bias is removed, a frame without stays as is."""
    from pathlib import Path

    from normpos_grasp.cell.config import load_cell
    from normpos_grasp.measure.depth_bias import check_frame_depth
    from normpos_grasp.sim.cell_scene import cell_camera, compose_cell_scene
    from normpos_grasp.sim.dataset import render_frame
    from normpos_grasp.sim.render import make_renderer

    cells = Path(__file__).resolve().parents[1] / "normpos_grasp" / "examples" / "cells"
    cell = load_cell(cells / "ur5e_bin_parallel.yaml")
    layout = compose_cell_scene(cell, 3, seed=4)
    cam = cell_camera(cell)
    renderer = make_renderer(layout, cam.width, cam.height, "raycast")
    try:
        sf = render_frame(layout, renderer, cam, sensor_preset("d435", depth_bias_m=bias), np.random.default_rng(2))
    finally:
        renderer.close()
    fixed, est = check_frame_depth(sf.frame, cell)
    assert est is not None and est.ok, est
    assert abs(est.bias_m - bias) < 0.001
    if bias == 0.0:
        assert fixed is sf.frame
    else:
        valid = sf.frame.depth_m > 0
        assert np.allclose(sf.frame.depth_m[valid] - fixed.depth_m[valid], est.bias_m)
