"""Hand-eye calibration: rendered boards with known truth in both modes, the excitation check, refused inputs,
POSES.csv round trip and bad rows, and the `calibrate hand-eye` command."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from normpos_grasp.camera import Camera
from normpos_grasp.camera.calibration import board_points, find_checkerboard
from normpos_grasp.camera.checkerboard import render_checkerboard
from normpos_grasp.camera.hand_eye import (
    EYE_IN_HAND,
    EYE_TO_HAND,
    HandEyeOptions,
    _canonical_order,
    calibrate_hand_eye,
    calibrate_hand_eye_from_corners,
    check_excitation,
    check_flange_poses,
    predict_corners,
    touch_check,
    verify_image,
)
from normpos_grasp.camera.hand_eye_io import read_flange_from_camera, read_poses_csv, write_poses_csv
from normpos_grasp.camera.hand_eye_synthetic import HandEyeScene, hand_eye_scene
from normpos_grasp.cli.calibrate_hand_eye import add_hand_eye_parser
from normpos_grasp.errors import CalibrationError, InputError
from normpos_grasp.geometry import invert_pose, make_pose, pose_to_ur, rotation_from_rotvec, transform_points
from normpos_grasp.geometry.transforms import rotation_angle

K = np.array([[615.0, 0, 320.5], [0, 612.0, 238.7], [0, 0, 1]])
CAM = Camera(K, 640, 480)
OBJ = board_points((9, 6), 0.025)


def _pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(mm, deg) between two poses."""
    d = invert_pose(a) @ b
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3]) * 1000.0), float(np.degrees(rotation_angle(d[:3, :3])))


def _vectors(poses: np.ndarray) -> np.ndarray:
    return np.array([pose_to_ur(p) for p in poses])


@pytest.mark.parametrize("mode", [EYE_TO_HAND, EYE_IN_HAND])
def test_rendered_boards_recover_the_truth(mode: str) -> None:
    """15 rendered boards (OpenCV's detector on the images), corners with 0.3 px added noise: within 1 mm / 0.1 deg."""
    rng = np.random.default_rng(7)
    scene = hand_eye_scene(rng, mode, 15)
    images = [render_checkerboard(CAM, c) for c in scene.camera_from_board]
    from_images = calibrate_hand_eye(CAM, images, _vectors(scene.base_from_flange), mode)
    mm, deg = _pose_error(scene.camera_pose, from_images.camera_pose)
    assert mm < 1.0 and deg < 0.1
    assert from_images.rms_px < 0.25  # detection error of rendered corners only
    corners: list[np.ndarray | None] = [None] * 15
    for i, view in zip(from_images.used, from_images.views, strict=True):
        corners[i] = view.corners_px + rng.normal(0.0, 0.3, view.corners_px.shape)
    result = calibrate_hand_eye_from_corners(CAM, corners, _vectors(scene.base_from_flange), mode)
    mm, deg = _pose_error(scene.camera_pose, result.camera_pose)
    assert mm < 1.0 and deg < 0.1
    bmm, bdeg = _pose_error(scene.board_pose, result.board_pose)
    assert bmm < 2.0 and bdeg < 0.2
    n = len(result.used)
    assert n >= 13 and len(result.used) + len(result.rejected) == 15
    for arr in (result.reprojection_rms_px, result.reprojection_max_px, result.consistency_mm, result.consistency_deg):
        assert arr.shape == (n,) and np.all(np.isfinite(arr))
    # 0.3 px per coordinate: about 0.42 px per corner, fitted with 12 parameters
    assert 0.33 < result.rms_px < 0.5
    assert np.all(result.reprojection_rms_px < 0.7)
    assert np.all(result.consistency_mm < 15.0) and np.all(result.consistency_deg < 1.0)
    # the 1-sigma reported by the refinement is of the size of the real error
    assert 0.02 < float(np.linalg.norm(result.std_position_mm)) < 1.0
    assert result.excitation.spread_deg[2] > 10.0 and not result.warnings
    lines = result.report_lines()
    assert len(lines) == 3 + n + len(result.rejected) + 1 and "RMS" in lines[-1]
    record = json.loads(json.dumps(result.to_dict()))
    assert len(record["poses"]) == n and record["mode"] == mode


def test_verification_touch_point_and_new_image() -> None:
    rng = np.random.default_rng(3)
    scene = hand_eye_scene(rng, EYE_IN_HAND, 12)
    images = [render_checkerboard(CAM, c) for c in scene.camera_from_board]
    result = calibrate_hand_eye(CAM, images, scene.base_from_flange, EYE_IN_HAND)
    truth = transform_points(scene.board_pose, OBJ)
    check = touch_check(result, truth[53] + [0.0005, 0.0, 0.0])
    assert check.corner == 53 and abs(check.distance_mm - 0.5) < 0.3
    assert touch_check(result, truth[0], corner=0).distance_mm < 0.3
    with pytest.raises(InputError, match="millimetres"):
        touch_check(result, truth[0] * 1000.0)
    with pytest.raises(InputError, match="corner"):
        touch_check(result, truth[0], corner=54)
    # a new flange pose: the corners land where predicted
    extra = hand_eye_scene(np.random.default_rng(99), EYE_IN_HAND, 1)
    new_flange = scene.board_pose @ invert_pose(extra.camera_from_board[0]) @ invert_pose(scene.camera_pose)
    image = render_checkerboard(CAM, extra.camera_from_board[0])
    ok = verify_image(result, CAM, image, pose_to_ur(new_flange))
    assert ok.rms_px < 0.3
    moved = new_flange @ make_pose(translation=[0.003, 0.0, 0.0])  # robot 3 mm off: pixels disagree
    assert verify_image(result, CAM, image, moved).rms_px > 2.0
    assert predict_corners(result, CAM, new_flange).shape == (54, 2)
    # eye-to-hand touch needs the board seen in the cell
    eth = hand_eye_scene(np.random.default_rng(4), EYE_TO_HAND, 12)
    eth_result = calibrate_hand_eye(
        CAM, [render_checkerboard(CAM, c) for c in eth.camera_from_board], eth.base_from_flange, EYE_TO_HAND
    )
    with pytest.raises(InputError, match="lay the board"):
        touch_check(eth_result, [0.5, 0.0, 0.0])
    laid = eth.camera_from_board[0]
    corner_true = transform_points(eth.camera_pose @ laid, OBJ[:1])[0]
    assert touch_check(eth_result, corner_true, 0, laid).distance_mm < 0.5


def _one_axis_poses(axis: tuple[float, float, float], angles_deg: np.ndarray) -> np.ndarray:
    base = make_pose(rotation_from_rotvec([np.pi, 0.0, 0.0]), [0.4, 0.1, 0.5])
    out = []
    for k, a in enumerate(angles_deg):
        rot = rotation_from_rotvec(np.radians(a) * np.asarray(axis))
        out.append(base @ make_pose(rot, [0.01 * k, -0.02 * k, 0.005 * k]))
    return np.stack(out)


def test_rotations_about_one_axis_are_refused_and_weak_sets_warned() -> None:
    poses = _one_axis_poses((0.0, 0.0, 1.0), np.linspace(-40, 40, 10))
    report = check_excitation(poses, EYE_IN_HAND)
    assert report.degenerate and "one axis" in report.message and "flange [0.00, 0.00, 1.00]" in report.message
    assert report.spread_deg[0] > 20 and report.spread_deg[1] < 0.01
    # corners that fit the poses exactly: still refused (the offset along the axis is unobservable)
    x = make_pose(rotation_from_rotvec([0.0, 0.0, 0.3]), [0.0, -0.06, 0.05])
    w = poses[0] @ x @ make_pose(translation=[-0.1, -0.06, 0.5])
    corners = [CAM.project(transform_points(invert_pose(x) @ invert_pose(p) @ w, OBJ)) for p in poses]
    with pytest.raises(CalibrationError, match="one axis") as err:
        calibrate_hand_eye_from_corners(CAM, corners, poses, EYE_IN_HAND)
    assert err.value.indices == tuple(range(10))
    small = check_excitation(_one_axis_poses((1.0, 0.0, 0.0), np.linspace(0, 3, 6)), EYE_TO_HAND)
    assert small.degenerate and "at most 3.0 deg" in small.message and small.frame == "base"
    # two axes, one of them weak: usable, with a warning naming what to add
    rng = np.random.default_rng(0)
    base = _one_axis_poses((1.0, 0.0, 0.0), np.zeros(1))[0]
    weak = np.stack(
        [
            base @ make_pose(rotation_from_rotvec(np.radians([rng.uniform(-25, 25), rng.uniform(-3, 3), 0.0])))
            for _ in range(10)
        ]
    )
    report = check_excitation(weak, EYE_IN_HAND)
    assert not report.degenerate and report.warnings and "add poses tilted" in report.warnings[0]


def test_impossible_inputs_are_refused() -> None:
    rng = np.random.default_rng(1)
    scene = hand_eye_scene(rng, EYE_IN_HAND, 6)
    vec = _vectors(scene.base_from_flange)
    corners = [CAM.project(transform_points(c, OBJ)) for c in scene.camera_from_board]
    mm = vec.copy()
    mm[:, :3] *= 1000.0
    with pytest.raises(InputError, match="millimetres"):
        calibrate_hand_eye_from_corners(CAM, corners, mm, EYE_IN_HAND)
    deg = vec.copy()
    deg[:, 3:] = np.degrees(deg[:, 3:]) + 10.0
    with pytest.raises(InputError, match="degrees"):
        check_flange_poses(deg)
    bad = vec.copy()
    bad[2, 4] = np.nan
    with pytest.raises(InputError, match="pose 2 holds NaN"):
        calibrate_hand_eye_from_corners(CAM, corners, bad, EYE_IN_HAND)
    with pytest.raises(InputError, match="corners for 6 images but 5 flange poses"):
        calibrate_hand_eye_from_corners(CAM, corners, vec[:5], EYE_IN_HAND)
    with pytest.raises(InputError, match="one pose per image"):
        calibrate_hand_eye(CAM, [np.zeros((480, 640), np.uint8)] * 2, vec[:3], EYE_IN_HAND)
    with pytest.raises(CalibrationError, match="found in 2 of 2 images, need 3"):
        calibrate_hand_eye_from_corners(CAM, corners[:2], vec[:2], EYE_IN_HAND)
    with pytest.raises(CalibrationError, match="found in 2 of 4") as err:
        calibrate_hand_eye_from_corners(CAM, [*corners[:2], None, None], vec[:4], EYE_IN_HAND)
    assert err.value.indices == (2, 3)
    with pytest.raises(InputError, match="mode"):
        calibrate_hand_eye_from_corners(CAM, corners, vec, "eye-on-hand")
    with pytest.raises(InputError, match="180 degrees"):
        HandEyeOptions(board=(8, 6))
    with pytest.raises(InputError, match="rigid"):
        check_flange_poses(np.stack([np.eye(4) * 2.0] * 3))
    # eye-in-hand data solved as eye-to-hand, or poses in the wrong order: the reprojection gate refuses them
    with pytest.raises(CalibrationError, match=r"the mode \(eye-to-hand\) is right"):
        calibrate_hand_eye_from_corners(CAM, corners, vec, EYE_TO_HAND)
    shuffled = vec[[1, 0, 3, 2, 5, 4]]
    with pytest.raises(CalibrationError, match="pose rows match the images"):
        calibrate_hand_eye_from_corners(CAM, corners, shuffled, EYE_IN_HAND)


def test_reversed_corner_order_is_corrected() -> None:
    scene = hand_eye_scene(np.random.default_rng(5), EYE_TO_HAND, 1)
    image = render_checkerboard(CAM, scene.camera_from_board[0])
    want = CAM.project(transform_points(scene.camera_from_board[0], OBJ))
    found = find_checkerboard(image, (9, 6))
    for start in (found, found[::-1].copy()):
        fixed = _canonical_order(image, start, (9, 6), 0.025)
        assert np.abs(fixed - want).max() < 0.3


def test_poses_csv_round_trip(tmp_path: Path) -> None:
    scene = hand_eye_scene(np.random.default_rng(2), EYE_TO_HAND, 5)
    path = tmp_path / "POSES.csv"
    write_poses_csv(path, scene.base_from_flange)
    text = path.read_text(encoding="utf-8")
    assert text.splitlines()[0] == "x,y,z,rx,ry,rz" and len(text.splitlines()) == 6
    back = read_poses_csv(path)
    np.testing.assert_allclose(back, _vectors(scene.base_from_flange), atol=1e-9)
    np.testing.assert_allclose(check_flange_poses(back), scene.base_from_flange, atol=1e-8)
    # a spreadsheet's byte-order mark, blank lines and spaces are fine
    path.write_text("\ufeffx, y, z, rx, ry, rz\n\n0.4, 0.1, 0.3, 3.1, 0, 0\n\n", encoding="utf-8")
    np.testing.assert_allclose(read_poses_csv(path), [[0.4, 0.1, 0.3, 3.1, 0.0, 0.0]])


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("", "is empty"),
        ("x,y,z,rx,ry\n1,2,3,4,5\n", "line 1: the header must be x,y,z,rx,ry,rz"),
        ("x,y,z,rx,ry,rz\n", "no poses"),
        ("x,y,z,rx,ry,rz\n0.1,0.2,0.3,0,0,0\n0.1,0.2,0.3,0,0\n", "line 3: expected 6 values"),
        ("x,y,z,rx,ry,rz\n0.1,0.2,abc,0,0,0\n", "line 2: z = 'abc' is not a number"),
        ("x,y,z,rx,ry,rz\n0.1,0.2,0.3,nan,0,0\n", "line 2: rx = nan is not finite"),
        ("x,y,z,rx,ry,rz\n412.3,-120.5,351.0,2.2,-2.2,0\n", "line 2: .*millimetres"),
        ("x,y,z,rx,ry,rz\n0.4,0.1,0.3,180,0,0\n", "line 2: .*degrees"),
    ],
)
def test_bad_poses_csv_rows(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "POSES.csv"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(InputError, match=message) as err:
        read_poses_csv(path)
    assert "\n" not in str(err.value)


def test_poses_csv_not_utf8_or_missing(tmp_path: Path) -> None:
    path = tmp_path / "POSES.csv"
    path.write_bytes(b"x,y,z,rx,ry,rz\n0.1,0.2,0.3,0,0,\xff\n")
    with pytest.raises(InputError, match="not UTF-8"):
        read_poses_csv(path)
    with pytest.raises(InputError, match="cannot read"):
        read_poses_csv(tmp_path / "missing.csv")


def _cli(argv: list[str]) -> int:
    """Run `calibrate hand-eye` through its own parser (the calibrate command registers the same one)."""
    parser = argparse.ArgumentParser(prog="calibrate")
    add_hand_eye_parser(parser.add_subparsers(dest="step"))
    args = parser.parse_args(["hand-eye", *argv])
    return int(args.handler(args))


def _write_set(tmp_path: Path, mode: str, n: int = 12, seed: int = 11) -> tuple[list[str], HandEyeScene]:
    import cv2

    scene = hand_eye_scene(np.random.default_rng(seed), mode, n)
    names = []
    for i, cfb in enumerate(scene.camera_from_board):
        name = tmp_path / f"view_{i:02d}.png"
        cv2.imwrite(str(name), render_checkerboard(CAM, cfb))
        names.append(str(name))
    write_poses_csv(tmp_path / "POSES.csv", scene.base_from_flange)
    CAM.save_json(tmp_path / "camera.json")
    return names, scene


def test_cli_eye_in_hand_writes_flange_from_camera(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    names, scene = _write_set(tmp_path, EYE_IN_HAND)
    out = tmp_path / "wrist.json"
    truth = transform_points(scene.board_pose, OBJ)[10]
    base = ["--mode", EYE_IN_HAND, "--images", *names, "--poses", str(tmp_path / "POSES.csv")]
    base += ["--board", "9x6", "--square", "0.025", "--camera", str(tmp_path / "camera.json"), "--out", str(out)]
    # a touch 5 mm off fails the verification: nothing written, exit 1
    assert _cli([*base, "--touch", *(str(v) for v in truth + [0.0, 0.005, 0.0])]) == 1
    assert "VERIFICATION FAILED" in capsys.readouterr().out and not out.exists()
    assert _cli([*base, "--touch", *(str(v) for v in truth)]) == 0
    printed = capsys.readouterr().out
    assert "touch check: corner 10" in printed and "wrote" in printed
    flange_from_camera = read_flange_from_camera(out)
    mm, deg = _pose_error(scene.camera_pose, flange_from_camera)
    assert mm < 1.0 and deg < 0.1
    cam = Camera.load_json(out)
    assert cam.world_from_camera is None and np.allclose(cam.K, CAM.K)
    report = json.loads((tmp_path / "wrist.hand_eye.json").read_text(encoding="utf-8"))
    assert report["mode"] == EYE_IN_HAND and report["checks"]["touch"]["corner"] == 10
    assert len(report["poses"]) + len(report["rejected"]) == 12 and len(report["poses"]) >= 10


def test_cli_eye_to_hand_writes_world_from_camera(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    names, scene = _write_set(tmp_path, EYE_TO_HAND, seed=12)
    out = tmp_path / "camera.json"  # the input camera is replaced
    argv = ["--mode", EYE_TO_HAND, "--images", *names, "--poses", str(tmp_path / "POSES.csv")]
    argv += ["--camera", str(out), "--out", str(out)]
    assert _cli(argv) == 0
    cam = Camera.load_json(out)
    assert cam.world_from_camera is not None
    mm, deg = _pose_error(scene.camera_pose, cam.world_from_camera)
    assert mm < 1.0 and deg < 0.1
    assert "robot base frame" in capsys.readouterr().out
    # one image too many: refused before anything is computed or written
    before = out.read_text(encoding="utf-8")
    with pytest.raises(InputError, match="13 images"):
        _cli([*argv[:2], "--images", *names, names[0], *argv[2 + 1 + len(names) :]])
    assert out.read_text(encoding="utf-8") == before
    with pytest.raises(InputError, match="needs --touch-image"):
        _cli([*argv, "--touch", "0.5", "0.0", "0.0"])
    with pytest.raises(InputError, match="needs --images, --camera, --out"):
        _cli(["--mode", EYE_TO_HAND, "--poses", str(tmp_path / "POSES.csv")])


def test_distorted_camera_recovers_the_truth() -> None:
    """Corners projected through OpenCV's distortion model: PnP and the refinement both apply the distortion."""
    cam = Camera(K, 640, 480, np.array([-0.12, 0.08, 0.001, -0.0005, -0.01]))
    rng = np.random.default_rng(21)
    scene = hand_eye_scene(rng, EYE_TO_HAND, 10)
    corners = [cam.project(transform_points(c, OBJ)) + rng.normal(0.0, 0.3, (54, 2)) for c in scene.camera_from_board]
    result = calibrate_hand_eye_from_corners(cam, corners, _vectors(scene.base_from_flange), EYE_TO_HAND)
    mm, deg = _pose_error(scene.camera_pose, result.camera_pose)
    assert mm < 1.0 and deg < 0.1 and result.rms_px < 0.5
    # the same corners read by a camera without distortion: the camera lands over 1 mm off
    plain = calibrate_hand_eye_from_corners(CAM, corners, _vectors(scene.base_from_flange), EYE_TO_HAND)
    assert _pose_error(scene.camera_pose, plain.camera_pose)[0] > 1.0


def test_cli_is_registered_under_calibrate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from normpos_grasp.cli.main import main

    names, scene = _write_set(tmp_path, EYE_IN_HAND, n=8, seed=13)
    argv = ["calibrate", "hand-eye", "--mode", EYE_IN_HAND, "--images", *names, "--poses", str(tmp_path / "POSES.csv")]
    argv += ["--camera", str(tmp_path / "camera.json"), "--out", str(tmp_path / "wrist.json")]
    assert main(argv) == 0
    mm, deg = _pose_error(scene.camera_pose, read_flange_from_camera(tmp_path / "wrist.json"))
    assert mm < 1.0 and deg < 0.1
    capsys.readouterr()
    assert main([*argv[:4], "--images", *names[:7], *argv[5 + len(names) :]]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds 8 poses but 7 images" in err
