"""A camera on the wrist (issue 19 item 2): the cell's `camera: {mount: wrist}` form, the frame transform at the
capture pose, the camera housing in the planner's collision world, and a wrist-camera cell picking in simulate."""

from __future__ import annotations

import copy
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.cell import BoxSpec, cell_from_dict, load_cell, resolve_cell
from normpos_grasp.cell.wrist_camera import CAMERA_SHAPE
from normpos_grasp.cli.main import main
from normpos_grasp.errors import CellConfigError, InputError, PlanningError
from normpos_grasp.execution import SafetyLimits
from normpos_grasp.io.yaml_safe import load_yaml_file
from normpos_grasp.kinematics.robot import Robot
from normpos_grasp.loop import run_cell_loop, wrist_capture
from normpos_grasp.planning.capture import plan_capture_move
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.templates.library import load_library

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_wrist_camera.yaml"
CELL = load_cell(EXAMPLE)


def _data() -> dict[str, Any]:
    data = load_yaml_file(EXAMPLE)
    assert isinstance(data, dict)
    return copy.deepcopy(data)


def _load(data: dict[str, Any]) -> Any:
    return cell_from_dict(data, base_dir=EXAMPLE.parent)


# ------------------------------------------------------------------------------------------------ the cell form


def test_example_cell_loads_with_the_calibrated_mount_and_the_housing_on_the_tool() -> None:
    raw = json.loads((EXAMPLE.parent / "ur5e_wrist_camera.camera.json").read_text())
    wrist = CELL.wrist_camera
    assert wrist is not None and CELL.world_from_camera is None
    assert np.allclose(wrist.flange_from_camera, raw["flange_from_camera"], atol=1e-6)
    assert wrist.capture_q.shape == (2, 6)
    body = next(s for s in CELL.tool.shapes if s.name == CAMERA_SHAPE)
    assert np.allclose(body.size, np.array([0.09, 0.025, 0.025]) + 2 * 0.01)  # housing + cable clearance
    # the box sits where the housing is: flange_from_tcp @ tcp_from_shape = flange_from_camera @ camera_from_body
    flange_from_box = CELL.tool.flange_from_tcp @ body.tcp_from_shape
    assert np.allclose(flange_from_box, wrist.flange_from_camera @ wrist.camera_from_body)
    assert resolve_cell("ur5e_wrist_camera").wrist_camera is not None  # packaged name


@pytest.mark.parametrize(
    ("patch", "path", "message"),
    [
        (lambda c: c.update(capture_poses=[]), "camera.capture_poses", "unknown key"),
        (lambda c: c.update(world_from_camera={"xyz": [0, 0, 1]}), "camera.world_from_camera", "unknown key"),
        (lambda c: c.update(mount="ceiling"), "camera.mount", "fixed, wrist"),
        (lambda c: c.pop("capture"), "camera.capture", "missing"),
        (lambda c: c.update(capture=[]), "camera.capture", "1 to 16"),
        (lambda c: c.update(capture=[[0.0] * 5]), "camera.capture[0]", "list of 6"),
        (lambda c: c.update(capture=[[0.0, -1.6, 1.4, -1.4, -1.57, 7.0]]), "camera.capture[0]", "joint limits"),
        (lambda c: c.update(flange_from_camera="missing.json"), "camera.flange_from_camera", "cannot read"),
        (lambda c: c.update(flange_from_camera={"xyz": [0.0, 0.9, 0.0]}), "camera.flange_from_camera", "0.5 m"),
        (lambda c: c.update(cable_clearance_m=0.5), "camera.cable_clearance_m", "outside"),
        (lambda c: c.update(body_size_m=[90, 25, 25]), "camera.body_size_m[0]", "millimetres"),
    ],
)
def test_bad_wrist_camera_keys_are_refused_naming_the_key(patch: Any, path: str, message: str) -> None:
    data = _data()
    patch(data["camera"])
    with pytest.raises(CellConfigError, match=message) as info:
        _load(data)
    assert info.value.path == path


def test_capture_pose_checks_tcp_workspace_floor_and_watch() -> None:
    data = _data()
    data["motion"]["workspace"]["max"][2] = 0.3  # the capture TCP is at z = 0.40 m
    with pytest.raises(CellConfigError, match="outside motion.workspace"):
        _load(data)
    data = _data()
    data["camera"]["capture"] = [[-0.2769, -0.2, 1.4236, -1.4117, -1.5708, -1.8477]]  # the arm leans into the table
    with pytest.raises(CellConfigError, match="under the floor|outside motion.workspace"):
        _load(data)
    data = _data()
    data["watch"] = {"arm_margin_m": 0.1}
    with pytest.raises(CellConfigError, match="fixed camera") as info:
        _load(data)
    assert info.value.path == "watch"


def test_cli_refuses_a_bad_wrist_camera_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = EXAMPLE.read_text().replace("  cable_clearance_m: 0.01", "  cable_clearence_m: 0.01")
    text = text.replace("ur5e_wrist_camera.camera.json", str(EXAMPLE.parent / "ur5e_wrist_camera.camera.json"))
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    code = main(["simulate", "--cell", str(bad), "--scenes", "1", "--out", str(tmp_path / "run"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "camera.cable_clearence_m" in err[0] and "did you mean 'cable_clearance_m'" in err[0]
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------------------------------- the frame transform


class _StillCamera:
    """A camera source that knows nothing of the arm: frames without extrinsics (like a live camera)."""

    def __init__(self) -> None:
        self.camera = Camera(np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]]), 640, 480)
        self.exhausted = False
        self.captures = 0

    def capture(self) -> RGBDFrame:
        self.captures += 1
        return RGBDFrame(np.zeros((480, 640, 3), np.uint8), np.zeros((480, 640)), self.camera)

    def check_pick(self, plan: PickPlan) -> str:
        return "not_checked"


def test_a_point_seen_from_two_capture_poses_lands_on_the_same_world_point() -> None:
    """The point's pixel and depth in each view come from an independent chain: pinocchio's base_from_flange at the
    capture joints and the camera JSON's flange_from_camera read as plain JSON; the loop's frame must map them
    back onto the one world point."""
    point = np.array([0.53, 0.04, 0.02])  # on the bin floor, m
    x_true = np.asarray(
        json.loads((EXAMPLE.parent / "ur5e_wrist_camera.camera.json").read_text())["flange_from_camera"]
    )
    robot = Robot.load("ur5e")
    source = _StillCamera()
    limits = SafetyLimits.from_cell(CELL)
    assert CELL.wrist_camera is not None
    seen = []
    start = np.asarray(CELL.home_q, dtype=np.float64)
    for view, q in enumerate(CELL.wrist_camera.capture_q):
        world_from_camera = CELL.world_from_base @ robot.fk(q) @ x_true
        camera_point = np.linalg.inv(world_from_camera) @ np.append(point, 1.0)
        pixel = source.camera.project(camera_point[None, :3])
        frame = wrist_capture(CELL, source, None, start, limits, view)  # dry run: the move is checked, not sent
        seen.append(frame.camera.backproject_to_world(pixel, camera_point[None, 2])[0])
        start = q
    for p in seen:
        assert np.linalg.norm(p - point) < 1e-5
    views = [CELL.wrist_camera.world_from_camera(CELL.world_from_base, "ur5e", q) for q in CELL.wrist_camera.capture_q]
    assert np.linalg.norm(views[0][:3, 3] - views[1][:3, 3]) > 0.05  # two different views of the point


def test_with_a_driver_the_frame_carries_the_pose_the_arm_reports() -> None:
    """The capture move runs on the simulated driver (10x time); the frame's pose is FK of the joints it reports."""
    from normpos_grasp.execution import DriverOptions, SimDriver

    limits = SafetyLimits.from_cell(CELL)
    driver = SimDriver(limits, q_home=np.asarray(CELL.home_q), time_scale=10.0, options=DriverOptions(watchdog_s=1.0))
    driver.connect()
    try:
        frame = wrist_capture(CELL, _StillCamera(), driver, np.asarray(CELL.home_q), limits, 0)
        q = driver.state().q
    finally:
        driver.disconnect()
        driver.shutdown()
    assert CELL.wrist_camera is not None
    assert np.max(np.abs(q - CELL.wrist_camera.capture_q[0])) < 1e-3
    expected = CELL.world_from_base @ Robot.load("ur5e").fk(q) @ CELL.wrist_camera.flange_from_camera
    assert frame.camera.world_from_camera is not None
    assert np.allclose(frame.camera.world_from_camera, expected, atol=1e-9)


# ------------------------------------------------------------------------------------- the housing in the planner


def test_the_camera_housing_is_in_the_collision_world() -> None:
    """A post just where the housing is at capture pose 0 (clear of the gripper and the arm): the cell file is
    refused naming the capture pose and the post; a cell holding it anyway gets no capture move; with the housing
    taken off the tool the same move plans."""
    assert CELL.wrist_camera is not None
    q = CELL.wrist_camera.capture_q[0]
    body = next(s for s in CELL.tool.shapes if s.name == CAMERA_SHAPE)
    flange = CELL.world_from_base @ Robot.load("ur5e").fk(q)
    centre = (flange @ CELL.tool.flange_from_tcp @ body.tcp_from_shape)[:3, 3]
    pose = np.eye(4)
    pose[:3, 3] = centre + [0.0, 0.0, 0.1]
    size = [0.02, 0.02, 0.16]
    data = _data()
    data["fixtures"] = [{"name": "post", "pose": {"xyz": pose[:3, 3].tolist()}, "size": size}]
    with pytest.raises(CellConfigError, match="camera housing included.*touches post") as info:
        _load(data)
    assert info.value.path == "camera.capture[0]"
    blocked = replace(CELL, static_boxes=(*CELL.static_boxes, BoxSpec("post", pose, np.array(size))))
    with pytest.raises(PlanningError, match=r"camera.capture\[0\].*goal configuration is in collision"):
        plan_capture_move(blocked, blocked.home_q, 0)
    bare = replace(
        blocked, tool=replace(blocked.tool, shapes=tuple(s for s in CELL.tool.shapes if s.name != CAMERA_SHAPE))
    )
    move = plan_capture_move(bare, bare.home_q, 0)
    assert np.allclose(move.capture_q, q) and move.trajectory.duration_s > 0
    with pytest.raises(InputError, match="does not exist"):
        plan_capture_move(CELL, CELL.home_q, 2)


class _NothingThere:
    def segment(self, frame: RGBDFrame) -> list[Any]:
        return []


def test_loop_tries_the_next_capture_pose_before_it_gives_up() -> None:
    """An empty view at capture pose 0 moves the (dry-run) arm to pose 1, captures and plans again from there."""
    source = _StillCamera()
    library = list(load_library(EXAMPLE.parents[1] / "templates" / "cube_40mm").templates)
    records = run_cell_loop(CELL, source, _NothingThere(), library, None, max_picks=1)
    assert CELL.wrist_camera is not None
    assert source.captures == 2 and [r.status for r in records] == ["no_feasible_grasp"]
    record = records[0]
    assert record.start_q is not None and np.allclose(record.start_q, CELL.wrist_camera.capture_q[1])
    assert record.captured is not None and record.captured.camera.world_from_camera is not None
    expected = CELL.wrist_camera.world_from_camera(CELL.world_from_base, "ur5e", CELL.wrist_camera.capture_q[1])
    assert np.allclose(record.captured.camera.world_from_camera, expected)


def test_loop_refuses_overlap_with_a_wrist_camera() -> None:
    with pytest.raises(InputError, match="fixed camera"):
        run_cell_loop(CELL, _StillCamera(), None, [], None, overlap=True)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------------- simulate


@pytest.mark.slow  # 2-5 s alone at load 5-8 on 2 cores (the pipeline's imports and kernels load here)
def test_a_wrist_camera_cell_plans_and_picks_in_simulate() -> None:
    """A part in the bin, rendered from capture pose 0 with the D435 noise model at 320x240, ideal masks: the pick
    is planned from the capture joints and held in physics (the scene is cleared)."""
    from normpos_grasp.simulate.episode import SimulationConfig, run_scene

    config = SimulationConfig(
        cell_path=str(EXAMPLE), segmenter="gt", parts=("box",), parts_per_scene=1, resolution=(320, 240)
    )
    result = run_scene(config, 0)
    assert result.picks, "no pick attempted"
    assert all(p.success for p in result.picks), [(p.part, p.cause, p.reason) for p in result.picks]
    assert result.cleared
