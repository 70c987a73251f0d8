"""Depth window estimate (Eq. 6-7), back-projection of masks, NormPosition summaries, GT segmenter, measure CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.camera import Camera, RGBDFrame
from normpos_grasp.camera.render import render, visible_mask
from normpos_grasp.errors import InputError, MeasurementError, SegmentationError
from normpos_grasp.geometry import make_pose, random_rotation, transform_points
from normpos_grasp.geometry.transforms import look_at
from normpos_grasp.io.bop import BopGT, BopScene, BopSceneWriter, load_mesh, read_models
from normpos_grasp.io.ply import read_ply, write_ply
from normpos_grasp.measure.depth import DepthFillOptions, fill_depth, valid_depth_mask
from normpos_grasp.measure.measure import (
    MeasureOptions,
    backproject_depth,
    measure_instance,
    measure_instances,
    normpos_to_dict,
    occupancy,
    oriented_box,
)
from normpos_grasp.perception.gt import GroundTruthSegmenter
from normpos_grasp.records.instance import Instance

K = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])


def _reference_fill(depth: np.ndarray, s: int, lo: float, hi: float) -> np.ndarray:
    """Eq. 6-7 by explicit loops (the definition)."""
    h, w = depth.shape
    out = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            win = depth[max(i - s, 0) : i + s + 1, max(j - s, 0) : j + s + 1]
            with np.errstate(invalid="ignore"):
                ok = np.isfinite(win) & (win > 0) & (win >= lo) & (win <= hi)
            if ok.any():
                out[i, j] = win[ok].mean()
    return out


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 3))
def test_window_mean_matches_definition(seed: int, s: int) -> None:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.2, 3.0, (13, 17))
    depth[rng.random(depth.shape) < 0.3] = 0.0
    depth[rng.random(depth.shape) < 0.05] = np.nan
    depth[rng.random(depth.shape) < 0.05] = np.inf
    depth[rng.random(depth.shape) < 0.05] = -1.0
    depth[rng.random(depth.shape) < 0.05] = 50.0  # beyond max range
    before = depth.copy()
    got = fill_depth(depth, DepthFillOptions(half_window=s, min_depth_m=0.1, max_depth_m=10.0))
    assert np.array_equal(before, depth, equal_nan=True)  # input untouched
    want = _reference_fill(depth, s, 0.1, 10.0)
    assert np.allclose(got, want, atol=2e-6)
    assert got.dtype == np.float64


def test_fill_only_keeps_valid_values_and_invalid_inputs() -> None:
    depth = np.full((9, 9), 1.0)
    depth[4, 4] = 0.0
    depth[0, 0] = 1.2
    out = fill_depth(depth, DepthFillOptions(half_window=1, fill_only=True))
    assert out[0, 0] == 1.2 and out[4, 4] == pytest.approx(1.0)
    assert not valid_depth_mask(np.array([[np.nan, -1.0, 0.0, np.inf, 0.01, 30.0, 1.0]])).any(axis=0)[:6].any()
    with pytest.raises(InputError, match="H, W"):
        fill_depth(np.zeros((3, 3, 3)))
    with pytest.raises(InputError, match="numeric"):
        fill_depth(np.array([["a"]]))
    with pytest.raises(InputError, match="half_window"):
        DepthFillOptions(half_window=-1)
    with pytest.raises(InputError, match="min_depth_m"):
        DepthFillOptions(min_depth_m=2.0, max_depth_m=1.0)
    with pytest.raises(InputError, match="min_valid"):
        DepthFillOptions(half_window=1, min_valid=10)


def test_edge_aware_does_not_fly_across_a_step() -> None:
    depth = np.full((40, 40), 1.0)  # table
    depth[10:30, 10:30] = 0.8  # box top, 20 cm higher
    depth[10:30, 30:32] = 0.0  # a hole at the border, like a stereo shadow
    plain = fill_depth(depth, DepthFillOptions(half_window=2))
    aware = fill_depth(depth, DepthFillOptions(half_window=2, edge_aware=True))
    between = (plain > 0.81) & (plain < 0.99)
    assert between.sum() > 50  # the paper's plain mean smears the edge
    ok = aware > 0
    assert not np.any((aware[ok] > 0.8 + 1e-6) & (aware[ok] < 1.0 - 1e-6))  # float32 sums: 1e-7 relative
    assert np.allclose(aware[15, 15], 0.8) and np.allclose(aware[2, 2], 1.0)
    # a slanted plane keeps its values (the slope limit accepts smooth surfaces)
    ramp = np.tile(np.linspace(0.6, 1.4, 80), (30, 1))
    assert np.allclose(fill_depth(ramp, DepthFillOptions(edge_aware=True))[5:-5, 5:-5], ramp[5:-5, 5:-5], atol=1e-6)


def _box_scene(camera: Camera, pose: np.ndarray) -> tuple[RGBDFrame, object, Instance]:
    box = trimesh.creation.box(extents=[0.12, 0.08, 0.05])
    rend = render(camera, [(box, pose)])
    frame = RGBDFrame(np.zeros((camera.height, camera.width, 3), np.uint8), rend.depth_m, camera)
    return frame, box, Instance(rend.mask(0), "box", 0.9, instance_id=3, source_id=7)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.booleans())
def test_measured_points_lie_on_the_surface(seed: int, distorted: bool, world: bool) -> None:
    rng = np.random.default_rng(seed)
    dist = np.array([0.05, -0.08, 0.001, -0.0005, 0.01]) if distorted else np.zeros(5)
    wfc = make_pose(random_rotation(rng), rng.uniform(-1, 1, 3)) if world else None
    cam = Camera(K, 160, 120, dist, world_from_camera=wfc)
    cfo = make_pose(random_rotation(rng), [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.5, 0.9)])
    frame, box, inst = _box_scene(cam, cfo)
    opts = MeasureOptions(depth=DepthFillOptions(half_window=0))
    (npos,) = measure_instances(frame, [inst], opts)
    assert npos.frame == ("world" if world else "camera")
    assert npos.instance_id == 3 and npos.label == "box" and npos.score == 0.9
    assert npos.n_points == inst.pixel_count
    pts_cam = npos.points if wfc is None else transform_points(np.linalg.inv(wfc), npos.points)
    pts_obj = transform_points(np.linalg.inv(cfo), pts_cam)
    _, d, _ = trimesh.proximity.closest_point(box, pts_obj)
    assert d.max() < 1e-6
    assert np.allclose(npos.centroid, npos.points.mean(axis=0))
    assert np.all(npos.aabb_min <= npos.points.min(axis=0)) and np.all(npos.aabb_max >= npos.points.max(axis=0))
    # normals: unit length and facing the viewpoint
    assert np.allclose(np.linalg.norm(npos.normals, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", npos.normals, npos.viewpoint - npos.points) > 0)
    # pixels back-project to the points
    back = backproject_depth(cam, frame.depth_m)[npos.pixels[:, 1], npos.pixels[:, 0]]
    assert np.allclose(back, pts_cam, atol=1e-9)


def test_normals_match_rendered_faces() -> None:
    cam = Camera(K, 160, 120)
    cfo = make_pose(look_at([0.3, -0.4, 0.6], [0, 0, 0])[:3, :3].T, [0.0, 0.0, 0.7])
    frame, box, inst = _box_scene(cam, cfo)
    rend = render(cam, [(box, cfo)])
    (npos,) = measure_instances(frame, [inst], MeasureOptions(depth=DepthFillOptions(half_window=0)))
    want = rend.normals_camera[npos.pixels[:, 1], npos.pixels[:, 0]]
    cos = np.einsum("ij,ij->i", want, npos.normals)
    assert np.median(cos) > 0.999 and np.mean(cos > 0.98) > 0.8  # face interiors exact, edges blend


def test_oriented_box_and_occupancy() -> None:
    rng = np.random.default_rng(0)
    rot = random_rotation(rng)
    local = rng.uniform(-1, 1, (4000, 3)) * [0.1, 0.05, 0.02]
    pts = local @ rot.T + [1.0, 2.0, 3.0]
    obb = oriented_box(pts)
    assert np.allclose(np.sort(obb.extents), [0.04, 0.1, 0.2], atol=0.005)
    assert np.linalg.det(obb.axes) == pytest.approx(1.0)
    loc = (pts - obb.center) @ obb.axes
    assert np.all(np.abs(loc) <= obb.extents / 2 + 1e-9)
    plane = np.column_stack([rng.uniform(0, 0.1, 20000), rng.uniform(0, 0.1, 20000), np.full(20000, 0.005)])
    occ = occupancy(plane, 0.01)
    assert occ.count == 100 and occ.volume_m3 == pytest.approx(100 * 1e-6)
    assert occ.centers().shape == (100, 3)
    with pytest.raises(InputError):
        occupancy(plane, 0.0)
    with pytest.raises(MeasurementError):
        oriented_box(np.zeros((0, 3)))


def test_measure_bad_input() -> None:
    cam = Camera(K, 160, 120)
    frame, _, inst = _box_scene(cam, make_pose(translation=[0, 0, 0.6]))
    empty = Instance(np.zeros((120, 160), bool), "none", 0.5, instance_id=1)
    far = Instance(inst.mask, "box", 1.0, instance_id=2)
    nodepth = RGBDFrame(frame.rgb, np.where(inst.mask, np.nan, frame.depth_m), cam)
    assert measure_instances(frame, [empty, inst]) and len(measure_instances(frame, [empty, inst])) == 1
    with pytest.raises(MeasurementError, match="empty mask"):
        measure_instance(frame, empty)
    with pytest.raises(MeasurementError, match="valid depth"):
        measure_instances(nodepth, [far], MeasureOptions(skip_failed=False))
    with pytest.raises(InputError, match="does not match"):
        measure_instance(frame, Instance(np.ones((10, 10), bool), "x", 1.0))
    with pytest.raises(InputError):
        MeasureOptions(erode_px=-1)
    eroded = measure_instance(frame, inst, MeasureOptions(erode_px=2))
    assert 0 < eroded.n_points < inst.pixel_count


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_ply_round_trip(seed: int, with_colors: bool) -> None:
    import tempfile

    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 50))
    pts = rng.normal(size=(n, 3))
    nrm = rng.normal(size=(n, 3)).astype(np.float32)
    col = rng.integers(0, 256, (n, 3), dtype=np.uint8) if with_colors else None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "p.ply"
        write_ply(path, pts, normals=nrm, colors=col)
        cloud = read_ply(path)
    assert np.array_equal(cloud.points, pts)
    assert cloud.normals is not None and np.array_equal(cloud.normals, nrm.astype(np.float64))
    assert (cloud.colors is None) == (col is None)
    if col is not None:
        assert np.array_equal(cloud.colors, col)


def test_json_summary_and_gt_segmenter_from_written_scene(tmp_path: Path) -> None:
    cam = Camera(K, 160, 120, world_from_camera=make_pose(translation=[0.1, 0.2, 1.0]))
    cfo = make_pose(translation=[0.0, 0.0, 0.6])
    frame, box, inst = _box_scene(cam, cfo)
    with BopSceneWriter(tmp_path / "000001") as writer:
        writer.add_frame(0, frame.rgb, frame.depth_m, cam, [BopGT(4, cfo)], [inst.mask], [inst.mask])
    scene = BopScene(tmp_path / "000001")
    loaded = scene.load_frame(0)
    (got,) = GroundTruthSegmenter(scene).segment(loaded)
    assert got.label == "obj_000004" and got.source_id == 0 and got.instance_id == 1
    assert np.array_equal(got.mask, inst.mask)
    (npos,) = measure_instances(loaded, [got])
    data = json.loads(json.dumps(normpos_to_dict(npos, "x.ply")))
    assert data["frame"] == "world" and data["points_file"] == "x.ply" and data["n_points"] == npos.n_points
    assert np.allclose(data["centroid_m"], npos.centroid, atol=1e-6)
    with pytest.raises(SegmentationError, match="not in"):
        GroundTruthSegmenter(scene).segment(RGBDFrame(loaded.rgb, loaded.depth_m, loaded.camera, im_id=5))


def test_lmo_can_points_lie_on_the_posed_model(lmo_sample: Path) -> None:
    scene = BopScene(lmo_sample / "test" / "000002")
    frame = scene.load_frame(3)
    instances = GroundTruthSegmenter(scene).segment(frame)
    assert [i.label for i in instances] == ["obj_000005"]  # only the can's model ships with the sample
    (npos,) = measure_instances(frame, instances)
    assert npos.frame == "camera" and npos.n_points > 3500
    mesh = load_mesh(read_models(lmo_sample / "models")[5])
    gt = scene.gt(3)[1]
    posed = mesh.copy()
    posed.apply_transform(gt.camera_from_object)
    _, dist, _ = trimesh.proximity.closest_point(posed, npos.points)
    assert np.mean(dist < 0.015) >= 0.9
    # the sample's depth reads ~7.4 mm far; centroid of the visible surface lies within a few cm of the can's
    # centre, on the camera side
    centre = gt.camera_from_object[:3, 3]
    assert np.linalg.norm(npos.centroid - centre) < 0.06
    assert npos.centroid[2] < centre[2]


def test_visible_mask_excludes_occluders(lmo_sample: Path) -> None:
    scene = BopScene(lmo_sample / "test" / "000002")
    frame = scene.load_frame(3)
    mesh = load_mesh(read_models(lmo_sample / "models")[5])
    rend = render(frame.camera, [(mesh, scene.gt(3)[1].camera_from_object)])
    vis = visible_mask(rend.depth_m, frame.depth_m)
    assert vis.sum() < rend.mask(0).sum() and vis.sum() > 0.9 * rend.mask(0).sum()
    with pytest.raises(InputError):
        visible_mask(rend.depth_m, frame.depth_m[1:])


def test_measure_cli_on_lmo(lmo_sample: Path, tmp_path: Path) -> None:
    import cv2

    from normpos_grasp.cli.main import main

    assert main(["measure", str(lmo_sample / "test"), "--out", str(tmp_path), "--segmenter", "gt"]) == 0
    data = json.loads((tmp_path / "000002" / "000003.json").read_text())
    assert data["scene_id"] == 2 and data["im_id"] == 3 and data["frame"] == "camera"
    (obj,) = data["objects"]
    assert {
        "instance_id",
        "label",
        "score",
        "n_points",
        "centroid_m",
        "aabb_min_m",
        "aabb_max_m",
        "points_file",
    } <= set(obj)
    assert set(data["timing_ms"]) >= {"total"}
    png = cv2.imread(str(tmp_path / "000002" / "000003_instances.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and set(np.unique(png).tolist()) == {0, 1}
    cloud = read_ply(tmp_path / "000002" / obj["points_file"])
    assert len(cloud.points) == obj["n_points"]
    assert main(["measure", str(tmp_path / "missing"), "--out", str(tmp_path)]) == 2
    assert main(["measure", str(lmo_sample / "test"), "--out", str(tmp_path), "--frames", "99"]) == 2


def test_measure_cli_other_segmenters(lmo_sample: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util
    import sys

    from normpos_grasp.cli.main import main

    if importlib.util.find_spec("normpos_grasp.perception.depth_segmenter") is not None:
        assert (
            main(["measure", str(lmo_sample / "test" / "000002"), "--out", str(tmp_path), "--segmenter", "depth"]) == 0
        )
        data = json.loads((tmp_path / "000002" / "000003.json").read_text())
        assert len(data["objects"]) >= 1 and all(o["n_points"] > 0 for o in data["objects"])
    # a segmenter module that is not installed gives exit code 2 and a clear error, not a traceback
    monkeypatch.setitem(sys.modules, "normpos_grasp.perception.depth_segmenter", None)
    assert main(["measure", str(lmo_sample / "test"), "--out", str(tmp_path), "--segmenter", "depth"]) == 2


def test_fill_region_must_match() -> None:
    depth = np.full((8, 8), 1.0)
    region = np.zeros((8, 8), bool)
    region[2:5, 2:5] = True
    out = fill_depth(depth, DepthFillOptions(half_window=1, edge_aware=True), region=region)
    assert np.allclose(out[region], 1.0)
    with pytest.raises(InputError, match="region"):
        fill_depth(depth, DepthFillOptions(edge_aware=True), region=region[1:])


def test_normpos_json_and_ply_export(tmp_path: Path) -> None:
    from normpos_grasp.measure.measure import save_normpos_json, save_normpos_ply

    cam = Camera(K, 160, 120)
    frame, _, inst = _box_scene(cam, make_pose(random_rotation(np.random.default_rng(8)), [0.0, 0.0, 0.6]))
    (npos,) = measure_instances(frame, [inst])
    save_normpos_json(tmp_path / "n.json", [npos])
    (entry,) = json.loads((tmp_path / "n.json").read_text())
    assert entry["instance_id"] == 3 and entry["frame"] == "camera" and entry["n_points"] == npos.n_points
    axes = np.array(entry["obb"]["axes"])
    assert np.allclose(axes, npos.obb.axes, atol=1e-6) and np.linalg.det(axes) == pytest.approx(1.0, abs=1e-5)
    save_normpos_ply(tmp_path / "n.ply", npos)
    cloud = read_ply(tmp_path / "n.ply")
    assert np.array_equal(cloud.points, npos.points)
    assert cloud.normals is not None and np.allclose(cloud.normals, npos.normals, atol=1e-6)
    occ = occupancy(npos, 0.01)
    assert occ.count > 0 and np.all(np.abs(occ.centers()[:, 2] - 0.6) < 0.1)
