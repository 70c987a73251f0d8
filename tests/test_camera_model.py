"""Projection / back-projection round trips (Eq. 1-5), serialisation and BOP camera entries."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.camera import Camera
from normpos_grasp.camera.model import check_world_from_camera
from normpos_grasp.errors import DatasetError, ExtrinsicsError, InputError
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


# ------------------------------------------------------------------------------ extrinsics that cannot be right
_R = make_pose(random_rotation(np.random.default_rng(7)), [0.3, -0.1, 0.9])


def _with(rot: np.ndarray | None = None, t: list[float] | None = None) -> np.ndarray:
    pose = _R.copy()
    if rot is not None:
        pose[:3, :3] = rot
    if t is not None:
        pose[:3, 3] = t
    return pose


BAD_EXTRINSICS = [
    ("zero rotation", _with(np.zeros((3, 3))), "not a rotation: max |R^T R - I| = 1 ", 1.0),
    ("rotation x1000", _with(_R[:3, :3] * 1000.0), "not a rotation", 1e6 - 1),
    ("reflection", _with(_R[:3, :3] @ np.diag([1.0, 1.0, -1.0])), "determinant -1.000", -1.0),
    ("swapped axes", _with(_R[:3, :3][:, [1, 0, 2]]), "a reflection", -1.0),
    ("off by 1 %", _with(_R[:3, :3] * 1.01), "tolerance 0.001", 0.0201),
    ("translation in mm", _with(t=[300.0, -100.0, 900.0]), "looks like millimetres", 953.9),
]


@pytest.mark.parametrize(("case", "pose", "phrase", "measured"), BAD_EXTRINSICS, ids=[b[0] for b in BAD_EXTRINSICS])
def test_extrinsics_that_cannot_be_right_are_refused(case: str, pose: np.ndarray, phrase: str, measured: float) -> None:
    with pytest.raises(ExtrinsicsError) as info:
        Camera(K, 640, 480, world_from_camera=pose)
    assert phrase in str(info.value), str(info.value)
    assert info.value.measured == pytest.approx(measured, rel=1e-3)
    with pytest.raises(ExtrinsicsError):
        Camera(K, 640, 480).with_extrinsics(pose)


def test_camera_under_the_floor_and_rounding() -> None:
    below = _with(t=[0.3, -0.1, -0.4])
    assert check_world_from_camera(below)[2, 3] == pytest.approx(-0.4)  # no floor given: allowed
    with pytest.raises(ExtrinsicsError, match="under the floor at z = 0.000 m") as info:
        check_world_from_camera(below, floor_z_m=0.0)
    assert info.value.measured == pytest.approx(-0.4)
    rounded = np.round(_R, 5)  # a file with 5 decimals: projected onto the nearest rotation, not refused
    fixed = check_world_from_camera(rounded)
    assert np.allclose(fixed[:3, :3] @ fixed[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.abs(fixed - _R).max() < 1e-4


def _bop_entry() -> dict:  # type: ignore[type-arg]
    return Camera(K, 640, 480, depth_scale_m=0.0001, world_from_camera=_R).to_bop()


@pytest.mark.parametrize(
    ("patch", "error", "phrase"),
    [
        (lambda e: e.update(cam_R_w2c=[0.0] * 9), ExtrinsicsError, "cam_R_w2c is not a rotation"),
        (lambda e: e.update(cam_R_w2c=[v * 1000 for v in e["cam_R_w2c"]]), ExtrinsicsError, "cam_R_w2c is not"),
        (lambda e: e.update(cam_t_w2c=[v * 1000 for v in e["cam_t_w2c"]]), ExtrinsicsError, "millimetres"),
        (lambda e: e.update(cam_K=[615.0, 0, 320.0]), InputError, "cam_K: expected shape (9,)"),
        (lambda e: e.update(cam_K="615 0 320"), InputError, "cam_K"),
        (lambda e: e.update(cam_R_w2c=[1, 0, 0, 0, 1, 0, 0, 0, "x"]), InputError, "cam_R_w2c"),
        (lambda e: e.pop("cam_t_w2c"), InputError, "only one of cam_R_w2c and cam_t_w2c"),
        (lambda e: e.update(depth_scale=float("inf")), InputError, "depth_scale_m must be finite"),
        (lambda e: e.update(depth_scale="0.1"), InputError, "depth_scale must be a number"),
    ],
)
def test_bop_camera_entries_are_validated(patch, error: type, phrase: str) -> None:  # type: ignore[no-untyped-def]
    entry = _bop_entry()
    Camera.from_bop(entry, 640, 480)  # the unpatched entry is valid
    patch(entry)
    with pytest.raises(error, match=re.escape(phrase)):
        Camera.from_bop(entry, 640, 480)


def test_camera_json_is_validated(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "camera.json"
    good = Camera(K, 640, 480, world_from_camera=_R).to_dict()
    for data, phrase in [
        ([1, 2, 3], "must be a JSON object"),
        ({**good, "width": "640"}, "width must be a whole number"),
        ({**good, "width": 60000}, "1..16384"),
        ({**good, "K": [[615.0, 0], [0, 615.0]]}, "K: expected shape (3, 3)"),
        ({**good, "world_from_camera": np.zeros((4, 4)).tolist()}, "last row"),
        ({**good, "world_from_camera": _with(np.zeros((3, 3))).tolist()}, "not a rotation"),
        ({k: v for k, v in good.items() if k != "K"}, "lacks the key 'K'"),
    ]:
        path.write_text(json.dumps(data))
        with pytest.raises(InputError, match=re.escape(phrase)) as info:
            Camera.load_json(path)
        assert str(info.value).startswith(f"camera file {path}") and "\n" not in str(info.value)
    path.write_bytes(b"\xff\xfe{")
    with pytest.raises(InputError, match="cannot read camera file"):
        Camera.load_json(path)


def test_bop_scene_with_a_zero_rotation_is_a_dataset_error(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from normpos_grasp.cli.main import main
    from normpos_grasp.io.bop import BopScene, BopSceneWriter

    scene_dir = tmp_path / "000001"
    cam = Camera(K, 640, 480, world_from_camera=_R).scaled(0.1)  # 64x48
    with BopSceneWriter(scene_dir, depth_scale_mm=0.1) as writer:
        writer.add_frame(0, np.zeros((48, 64, 3), np.uint8), np.full((48, 64), 0.9), cam, [], [], [])
    cams = json.loads((scene_dir / "scene_camera.json").read_text())
    cams["0"]["cam_R_w2c"] = [0.0] * 9
    (scene_dir / "scene_camera.json").write_text(json.dumps(cams))
    with pytest.raises(DatasetError, match=r"frame 0: cam_R_w2c is not a rotation"):
        BopScene(scene_dir).camera(0)
    out = tmp_path / "measured"
    code = main(["measure", str(scene_dir), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "cam_R_w2c is not a rotation" in err, err
    assert not out.exists() or not any(out.rglob("*.*"))
