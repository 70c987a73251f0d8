"""BOP reader/writer: the real LM-O frame (golden numbers from its files), write/read round trips, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from normpos_grasp.camera import Camera
from normpos_grasp.errors import DatasetError, InputError
from normpos_grasp.geometry import make_pose, random_rotation
from normpos_grasp.io.bop import BopGT, BopScene, BopSceneWriter, load_mesh, read_models, read_split, write_models

K = np.array([[600.0, 0, 79.5], [0, 600.0, 59.5], [0, 0, 1]])


def test_lmo_scene_camera_depth_gt(lmo_sample: Path) -> None:
    scenes = read_split(lmo_sample / "test")
    assert [s.scene_id for s in scenes] == [2]
    scene = scenes[0]
    assert scene.frame_ids == [3]
    cam = scene.camera(3)
    assert (cam.width, cam.height) == (640, 480)
    assert cam.fx == pytest.approx(572.4114) and cam.cy == pytest.approx(242.04899)
    assert cam.depth_scale_m == pytest.approx(0.001)
    frame = scene.load_frame(3)
    assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
    raw = scene.load_depth_raw(3)
    assert np.array_equal(frame.depth_m, raw * 0.001)
    gts = scene.gt(3)
    assert [g.obj_id for g in gts] == [1, 5, 6, 8, 9, 10, 11, 12]
    can = gts[1].camera_from_object
    assert np.allclose(can[:3, 3], [0.13436598053, 0.04577287271, 0.96478389285])
    assert np.linalg.det(can[:3, :3]) == pytest.approx(1.0)
    with pytest.raises(DatasetError, match="scene_gt_info"):
        scene.gt_info(3)
    with pytest.raises(DatasetError, match="mask"):
        scene.mask_visib(3, 0)
    with pytest.raises(DatasetError, match="not in"):
        scene.camera(4)


def test_an_itodd_style_scene_reads_like_its_png_twin(lmo_sample: Path, tmp_path: Path) -> None:
    """ITODD stores gray/*.tif and depth/*.tif (16-bit): the LM-O frame rewritten so reads the same depth and a
    gray image replicated to 3 channels; a float TIFF depth is refused naming the file."""
    import shutil

    import cv2

    src = lmo_sample / "test" / "000002"
    dst = tmp_path / "test" / "000002"
    (dst / "gray").mkdir(parents=True)
    (dst / "depth").mkdir()
    shutil.copy(src / "scene_camera.json", dst / "scene_camera.json")
    png = BopScene(src)
    raw = png.load_depth_raw(3)
    gray = cv2.cvtColor(png.load_rgb(3), cv2.COLOR_RGB2GRAY)
    assert cv2.imwrite(str(dst / "depth" / "000003.tif"), raw)
    assert cv2.imwrite(str(dst / "gray" / "000003.tif"), gray)
    tif = read_split(tmp_path / "test")[0]
    assert np.array_equal(tif.load_depth_raw(3), raw)
    frame = tif.load_frame(3)
    assert np.array_equal(frame.depth_m, png.load_frame(3).depth_m)
    assert frame.rgb.shape == (480, 640, 3) and np.array_equal(frame.rgb[:, :, 0], gray)
    assert cv2.imwrite(str(dst / "depth" / "000003.tif"), raw.astype(np.float32))
    with pytest.raises(DatasetError, match="000003.tif decodes as float32"):
        BopScene(dst).load_depth_raw(3)


def test_lmo_models(lmo_sample: Path) -> None:
    models = read_models(lmo_sample / "models")
    can = models[5]
    assert can.diameter_m == pytest.approx(0.2014035855)
    assert np.allclose(can.extents_m, [0.1007916, 0.1817958, 0.1937340], atol=1e-6)
    mesh = load_mesh(can)
    assert np.allclose(mesh.bounds[0], can.min_m, atol=1e-6)
    assert np.allclose(mesh.extents, can.extents_m, atol=1e-6)


def _scene(rng: np.random.Generator, n_frames: int, tmp: Path, extrinsics: bool) -> list[dict]:
    frames = []
    wfc = make_pose(random_rotation(rng), rng.uniform(-1, 1, 3)) if extrinsics else None
    cam = Camera(K, 160, 120, world_from_camera=wfc)
    with BopSceneWriter(tmp, depth_scale_mm=0.1) as writer:
        for im_id in range(n_frames):
            rgb = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
            depth = rng.uniform(0.3, 2.0, (120, 160))
            depth[rng.random((120, 160)) < 0.1] = 0.0
            gts = [BopGT(int(rng.integers(1, 30)), make_pose(random_rotation(rng), rng.uniform(-0.2, 0.2, 3)))]
            full = rng.random((120, 160)) < 0.3
            vis = full & (rng.random((120, 160)) < 0.5)
            writer.add_frame(im_id * 7, rgb, depth, cam, gts, [full], [vis])
            frames.append({"im_id": im_id * 7, "rgb": rgb, "depth": depth, "gt": gts, "full": full, "vis": vis})
    return frames


@pytest.mark.parametrize("extrinsics", [False, True])
def test_writer_round_trip(tmp_path: Path, extrinsics: bool) -> None:
    rng = np.random.default_rng(5)
    frames = _scene(rng, 3, tmp_path / "000004", extrinsics)
    scene = read_split(tmp_path)[0]
    assert scene.scene_id == 4
    assert scene.frame_ids == [0, 7, 14]
    for f in frames:
        im_id = f["im_id"]
        cam = scene.camera(im_id)
        assert (cam.width, cam.height) == (160, 120)
        assert (cam.world_from_camera is not None) == extrinsics
        frame = scene.load_frame(im_id)
        assert np.array_equal(frame.rgb, f["rgb"])
        assert np.abs(frame.depth_m - f["depth"]).max() <= 0.5e-4 + 1e-12  # 0.1 mm quantisation
        assert np.array_equal(frame.depth_m == 0, f["depth"] == 0)
        (gt,) = scene.gt(im_id)
        assert gt.obj_id == f["gt"][0].obj_id
        assert np.allclose(gt.camera_from_object, f["gt"][0].camera_from_object, atol=1e-8)
        assert np.array_equal(scene.mask_visib(im_id, 0), f["vis"])
        assert np.array_equal(scene.mask(im_id, 0), f["full"])
        (info,) = scene.gt_info(im_id)
        assert info["px_count_all"] == int(f["full"].sum())
        assert info["px_count_visib"] == int(f["vis"].sum())
        assert info["px_count_valid"] == int((f["vis"] & (f["depth"] > 0)).sum())
        assert info["visib_fract"] == pytest.approx(f["vis"].sum() / f["full"].sum())
        ys, xs = np.nonzero(f["vis"])
        assert info["bbox_visib"] == [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]


def test_writer_is_deterministic(tmp_path: Path) -> None:
    _scene(np.random.default_rng(11), 2, tmp_path / "a" / "000001", True)
    _scene(np.random.default_rng(11), 2, tmp_path / "b" / "000001", True)
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert files_a == files_b and len(files_a) == 3 + 2 * 4
    for rel in files_a:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes(), rel
    data = json.loads((tmp_path / "a" / "000001" / "scene_gt_info.json").read_text())
    assert list(data) == ["0", "7"]


def test_writer_empty_visible_mask_and_bad_input(tmp_path: Path) -> None:
    cam = Camera(K, 160, 120)
    rgb = np.zeros((120, 160, 3), np.uint8)
    depth = np.full((120, 160), 1.0)
    depth[0, 0] = np.nan
    depth[0, 1] = -1.0
    depth[0, 2] = np.inf
    empty = np.zeros((120, 160), bool)
    writer = BopSceneWriter(tmp_path / "000000")
    writer.add_frame(0, rgb, depth, cam, [BopGT(1, np.eye(4))], [empty], [empty])
    with pytest.raises(InputError, match="unique"):
        writer.add_frame(0, rgb, depth, cam, [], [], [])
    with pytest.raises(InputError, match="rgb"):
        writer.add_frame(1, rgb[:, :, 0], depth, cam, [], [], [])
    with pytest.raises(InputError, match="depth_m"):
        writer.add_frame(1, rgb, depth[1:], cam, [], [], [])
    with pytest.raises(InputError, match="one mask"):
        writer.add_frame(1, rgb, depth, cam, [BopGT(1, np.eye(4))], [], [])
    with pytest.raises(InputError, match="overflows"):
        writer.add_frame(1, rgb, np.full((120, 160), 7.0), cam, [], [], [])
    with pytest.raises(InputError, match="distortion"):
        writer.add_frame(1, rgb, depth, Camera(K, 160, 120, np.array([0.1, 0, 0, 0, 0])), [], [], [])
    with pytest.raises(InputError, match="bool"):
        writer.add_frame(1, rgb, depth, cam, [BopGT(1, np.eye(4))], [empty.astype(np.uint8)], [empty])
    writer.close()
    writer.close()
    with pytest.raises(InputError, match="closed"):
        writer.add_frame(2, rgb, depth, cam, [], [], [])
    scene = BopScene(tmp_path / "000000")
    d = scene.load_depth(0)
    assert d[0, 0] == 0 and d[0, 1] == 0 and d[0, 2] == 0 and d[5, 5] == pytest.approx(1.0)
    (info,) = scene.gt_info(0)
    assert info["bbox_visib"] == [-1, -1, -1, -1] and info["visib_fract"] == 0.0
    with pytest.raises(InputError, match="depth_scale_mm"):
        BopSceneWriter(tmp_path / "x", depth_scale_mm=0)


def test_reader_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        BopScene(tmp_path / "nope")
    (tmp_path / "000001").mkdir()
    with pytest.raises(DatasetError, match="scene_camera.json"):
        BopScene(tmp_path / "000001")
    with pytest.raises(DatasetError, match="no BOP scene"):
        read_split(tmp_path)
    (tmp_path / "000001" / "scene_camera.json").write_text("{not json")
    with pytest.raises(DatasetError, match="cannot read"):
        BopScene(tmp_path / "000001")
    (tmp_path / "000001" / "scene_camera.json").write_text('{"a": {}}')
    with pytest.raises(DatasetError, match="integer"):
        BopScene(tmp_path / "000001")
    (tmp_path / "000001" / "scene_camera.json").write_text('{"0": {"cam_K": [1, 0, 0, 0, 1, 0, 0, 0, 1]}}')
    scene = BopScene(tmp_path / "000001")
    with pytest.raises(DatasetError, match="neither"):
        scene.camera(0)
    with pytest.raises(DatasetError, match="no ground truth"):
        scene.gt(0)
    (tmp_path / "000001" / "scene_gt.json").write_text('{"0": [{"obj_id": 1}]}')
    with pytest.raises(DatasetError, match="cam_R_m2c"):
        BopScene(tmp_path / "000001").gt(0)


def test_models_round_trip(tmp_path: Path) -> None:
    import trimesh

    box = trimesh.creation.box(extents=[0.04, 0.06, 0.1])
    box.apply_translation([0.01, 0.0, 0.0])
    flip = make_pose(np.diag([-1.0, -1.0, 1.0]), [0.02, 0.0, 0.0])
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=64)
    write_models(tmp_path, [(3, box, [flip], None), (12, cyl, None, [((0, 0, 2.0), (0, 0, 0.01))])])
    models = read_models(tmp_path)
    assert sorted(models) == [3, 12]
    assert np.allclose(models[3].extents_m, [0.04, 0.06, 0.1])
    assert models[3].diameter_m == pytest.approx(float(np.linalg.norm([0.04, 0.06, 0.1])))
    assert np.allclose(models[3].symmetries_discrete[0], flip)
    axis, offset = models[12].symmetries_continuous[0]
    assert np.allclose(axis, [0, 0, 1]) and np.allclose(offset, [0, 0, 0.01])
    info = json.loads((tmp_path / "models_info.json").read_text())
    assert info["3"]["size_z"] == pytest.approx(100.0)
    assert info["12"]["symmetries_continuous"][0]["offset"][2] == pytest.approx(10.0)
    loaded = load_mesh(models[3])
    assert np.allclose(loaded.bounds, box.bounds, atol=1e-9)
    first = (tmp_path / "models_info.json").read_bytes()
    write_models(tmp_path, [(3, box, [flip], None), (12, cyl, None, [((0, 0, 2.0), (0, 0, 0.01))])])
    assert (tmp_path / "models_info.json").read_bytes() == first
    with pytest.raises(InputError, match="unique"):
        write_models(tmp_path, [(3, box, None, None), (3, box, None, None)])
    with pytest.raises(DatasetError, match="not found"):
        load_mesh(models[3].__class__(99, tmp_path / "obj_000099.ply", 0.1, np.ones(3)))
