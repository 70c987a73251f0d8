"""Sensor models: depth RMS vs formula on a rendered plane, holes (left band, shadows, range), determinism."""

from __future__ import annotations

import mujoco  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import pytest
import trimesh  # noqa: F401  (a hard dependency: imported, never skipped)

import normpos_grasp.sim  # noqa: F401  (sets MUJOCO_GL=egl before mujoco loads)
from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import make_pose
from normpos_grasp.sim.cameras import INTRINSICS, camera_intrinsics, camera_pose
from normpos_grasp.sim.parts import part_library_by_name
from normpos_grasp.sim.render import Rendering, render
from normpos_grasp.sim.scene import SceneLayout, SceneOptions, static_boxes
from normpos_grasp.sim.sensor import SENSOR_PRESETS, sensor_preset

PLANE = SceneLayout((), np.zeros((0, 4, 4)), static_boxes(SceneOptions(container="table", table_size_m=(8, 8))))


def _plane_view(sensor: str, z: float) -> tuple[Rendering, object]:
    cam = camera_intrinsics(sensor, (640, 480)).with_extrinsics(camera_pose([0, 0, 0], z, 0.0, 0.0))
    return render(PLANE, cam), cam


IN_RANGE = [
    (sensor, z)
    for sensor in ("d435", "d455", "zed2", "zivid")
    for z in (0.5, 1.0, 2.0)
    if sensor_preset(sensor).min_range_m < z < sensor_preset(sensor).max_range_m
]


@pytest.mark.parametrize(("sensor", "z"), IN_RANGE)
def test_plane_rms_matches_formula(sensor: str, z: float) -> None:
    model = sensor_preset(sensor)
    ideal, cam = _plane_view(sensor, z)
    _, depth = model.apply(ideal, cam, np.random.default_rng(3))
    valid = depth > 0
    assert valid.mean() > 0.7
    rms = np.sqrt(np.mean((depth[valid] - z) ** 2))
    expected = float(model.depth_rms_m(z, cam.fx))
    assert rms == pytest.approx(expected, rel=0.10)
    # the noise-only formula sigma(z) = z^2 sigma_d / (f B) (+ floor + proportional term)
    sigma = model.noise_floor_m + model.noise_per_m * z
    if model.baseline_m > 0:
        sigma += z * z * model.disparity_noise_px / (cam.fx * model.baseline_m)
    assert float(model.depth_sigma_m(z, cam.fx)) == pytest.approx(sigma)


def test_d435_reproduces_the_reference_figures() -> None:
    model = sensor_preset("d435")
    fx = INTRINSICS["d435"].fx
    for z, mm in ((0.5, 0.9), (1.0, 3.6), (2.0, 14.0)):
        assert float(model.depth_sigma_m(z, fx)) * 1000 == pytest.approx(mm, rel=0.05)
    assert float(sensor_preset("d455").depth_sigma_m(1.0, INTRINSICS["d455"].fx)) * 1000 == pytest.approx(1.9, rel=0.05)
    assert float(sensor_preset("zed2").depth_sigma_m(1.0, INTRINSICS["zed2"].fx)) * 1000 == pytest.approx(2.8, rel=0.05)


def test_left_band_width_follows_disparity() -> None:
    model = sensor_preset("d435", dropout_prob=0.0, edge_hole_prob=0.0, grazing_deg=90.0)
    for z in (0.5, 1.0):
        ideal, cam = _plane_view("d435", z)
        _, depth = model.apply(ideal, cam, np.random.default_rng(0))
        band = cam.fx * model.baseline_m / z  # pixels the second imager cannot see
        cols_invalid = (depth == 0).all(axis=0)
        assert cols_invalid[: int(band) - 1].all()
        assert not cols_invalid[int(np.ceil(band)) + 1 :].any()


def test_occlusion_shadow_left_of_a_near_object() -> None:
    cube = part_library_by_name()["cube"]
    layout = SceneLayout((cube,), make_pose(translation=[0, 0, 0.02])[None], PLANE.static_boxes)
    cam = camera_intrinsics("d435", (640, 480)).with_extrinsics(camera_pose([0, 0, 0], 0.6, 0.0, 0.0))
    ideal = render(layout, cam)
    model = sensor_preset("d435", dropout_prob=0.0, edge_hole_prob=0.0, grazing_deg=90.0, disparity_noise_px=0.0)
    _, depth = model.apply(ideal, cam, np.random.default_rng(0))
    rows = np.nonzero(ideal.masks_visible[0].any(axis=1))[0]
    row = rows[len(rows) // 2]
    cols = np.nonzero(ideal.masks_visible[0][row])[0]
    left = cols.min()
    # the table strip just left of the cube is hidden from the second imager: width fB (1/z_table - 1/z_top)
    width = cam.fx * model.baseline_m * (1 / 0.6 - 1 / 0.56)
    assert (depth[row, left - int(width) + 1 : left] == 0).all()
    assert (depth[row, left - int(width) - 3 : left - int(width) - 1] > 0).all()
    assert (depth[row, cols] > 0).all()  # the cube top itself is measured


def test_range_limits_quantisation_and_determinism() -> None:
    ideal, cam = _plane_view("d435", 1.0)
    model = sensor_preset("d435")
    rgb1, d1 = model.apply(ideal, cam, np.random.default_rng(5))
    rgb2, d2 = model.apply(ideal, cam, np.random.default_rng(5))
    assert np.array_equal(d1, d2) and np.array_equal(rgb1, rgb2)
    _, d3 = model.apply(ideal, cam, np.random.default_rng(6))
    assert not np.array_equal(d1, d3)
    v = d1 > 0
    np.testing.assert_allclose(d1[v] / 0.001, np.round(d1[v] / 0.001), atol=1e-6)  # 1 mm steps
    near = sensor_preset("d435", min_range_m=1.5)
    assert not np.any(near.apply(ideal, cam, np.random.default_rng(0))[1] > 0)
    assert rgb1.dtype == np.uint8 and rgb1.shape == ideal.rgb.shape
    assert not np.array_equal(rgb1, ideal.rgb)
    # the rendering is left untouched
    assert np.all(ideal.depth_m[ideal.depth_m > 0] == pytest.approx(1.0, abs=1e-6))


def test_ideal_preset_is_exact() -> None:
    ideal, cam = _plane_view("ideal", 0.8)
    rgb, depth = sensor_preset("ideal").apply(ideal, cam, np.random.default_rng(0))
    assert np.array_equal(depth, ideal.depth_m) and np.array_equal(rgb, ideal.rgb)


def test_presets_and_validation() -> None:
    assert set(SENSOR_PRESETS) == {"ideal", "d435", "d455", "zed2", "zivid"}
    assert set(SENSOR_PRESETS) <= set(INTRINSICS)
    with pytest.raises(InputError, match="unknown sensor"):
        sensor_preset("kinect9")
    with pytest.raises(InputError, match="baseline"):
        sensor_preset("ideal", disparity_noise_px=0.1)


def test_material_dropout_hits_only_that_material() -> None:
    lib = part_library_by_name()
    plate, box = lib["plate"], lib["box"]  # aluminium and ABS
    poses = np.stack([make_pose(translation=[-0.05, 0, 0.004]), make_pose(translation=[0.05, 0, 0.015])])
    layout = SceneLayout((plate, box), poses, PLANE.static_boxes)
    cam = camera_intrinsics("d435", (640, 480)).with_extrinsics(camera_pose([0, 0, 0], 0.4, 0.0, 0.0))
    ideal = render(layout, cam)
    assert ideal.part_materials == ("aluminium", "abs")
    clean = dict(dropout_prob=0.0, edge_hole_prob=0.0, grazing_deg=90.0, shadows=False)
    model = sensor_preset("d435", material_dropout=(("aluminium", 0.3),), **clean)
    lost_plate, lost_box = [], []
    for seed in range(4):
        _, depth = model.apply(ideal, cam, np.random.default_rng(seed))
        lost_plate.append(float((depth[ideal.masks_visible[0]] == 0).mean()))
        lost_box.append(float((depth[ideal.masks_visible[1]] == 0).mean()))
    assert np.mean(lost_plate) == pytest.approx(0.3, abs=0.1)
    assert max(lost_box) == 0.0
    _, depth = sensor_preset("d435", material_dropout=(), **clean).apply(ideal, cam, np.random.default_rng(0))
    assert (depth[ideal.masks_visible[0]] > 0).all()
