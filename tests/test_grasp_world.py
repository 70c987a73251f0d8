"""CollisionWorld: categories, scoped without/holding, clutter voxels, arm self-collision, tool opening, cell YAML."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import cell_from_dict, load_cell
from normpos_grasp.collision import CollisionWorld, tool_from_gripper
from normpos_grasp.errors import CellConfigError
from normpos_grasp.geometry import make_pose
from normpos_grasp.kinematics import Gripper, Robot
from normpos_grasp.planning import ArmModel

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
DOWN = np.diag([1.0, -1.0, -1.0])  # TCP z pointing down


def _tool_world() -> CollisionWorld:
    world = CollisionWorld()
    world.set_tool(tool_from_gripper(Gripper.load("2f85")))
    return world


def test_tool_hits_by_category_and_disable() -> None:
    world = _tool_world()
    world.add_box("table", make_pose(None, [0, 0, -0.025]), [1, 1, 0.05], "cell")
    cube = trimesh.creation.box((0.04, 0.04, 0.04))
    world.add_mesh("object/0", cube, make_pose(None, [0.3, 0, 0.02]), "object")
    above = make_pose(DOWN, [0.0, 0.0, 0.3])
    assert world.check_tool(above, 0.06) is None
    # tool pushed into the table
    hit = world.check_tool(make_pose(DOWN, [0.0, 0.0, 0.0]), 0.06)
    assert hit is not None and hit.reason == "collision_cell"
    # jaws open around the cube at grasp depth: free; closed onto it: the fingers hit the object
    grasp = make_pose(DOWN, [0.3, 0.0, 0.03])
    assert world.check_tool(grasp, 0.06) is None
    hit = world.check_tool(grasp, 0.02)
    assert hit is not None and hit.reason == "collision_object"
    with world.without("object/0"):
        assert world.check_tool(grasp, 0.02) is None
        with world.without("object/0", "no such element"):  # nested, unknown names ignored
            assert world.check_tool(grasp, 0.02) is None
        assert not world.is_enabled("object/0")
    assert world.check_tool(grasp, 0.02) is not None
    # the scope is restored when the block raises
    with pytest.raises(RuntimeError), world.without("object/0"):
        raise RuntimeError("planner failed")
    assert world.is_enabled("object/0") and world.check_tool(grasp, 0.02) is not None
    # a moved element is queried where it now is (the cached broad phase is rebuilt)
    world.move("object/0", make_pose(None, [0.6, 0.0, 0.02]))
    assert world.check_tool(grasp, 0.02) is None
    assert world.check_tool(make_pose(DOWN, [0.6, 0.0, 0.03]), 0.02) is not None


def test_unexplained_points_become_clutter_voxels() -> None:
    world = _tool_world()
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.02, -0.02, 0.0], [0.02, 0.02, 0.01], (500, 3))
    n = world.add_points("clutter/1", pts, voxel_m=0.01)
    assert 4 <= n <= 75
    hit = world.check_tool(make_pose(DOWN, [0.0, 0.0, 0.01]), 0.0)
    assert hit is not None and hit.reason == "collision_clutter"
    assert world.check_tool(make_pose(DOWN, [0.3, 0.0, 0.01]), 0.0) is None


def test_inflated_tool_reports_clearance() -> None:
    world = _tool_world()
    world.add_box("wall", make_pose(None, [0.0, 0.1, 0.1]), [0.5, 0.01, 0.2], "cell")
    # the palm is 75 mm wide along y: its face is 7.5 mm from the wall's (y = 0.095) with the TCP at y = 0.05
    pose = make_pose(DOWN, [0.0, 0.05, 0.1])
    assert world.check_tool(pose, 0.05) is None
    assert world.check_tool(pose, 0.05, inflated=True) is not None


def test_arm_self_collision_and_link_placement_match_kinematics() -> None:
    arm = ArmModel.from_name("ur5e")
    robot = Robot.load("ur5e")
    rng = np.random.default_rng(1)
    for _ in range(5):
        q = rng.uniform(-3, 3, 6)
        ours = arm.shape_poses(q)
        links = robot.link_poses(q)
        for pose, shape in zip(ours, robot.collision_geometry, strict=True):
            np.testing.assert_allclose(pose, links[shape.link] @ shape.link_from_shape, atol=1e-12)
    world = CollisionWorld()
    world.set_arm(arm)
    world.set_tool(tool_from_gripper(Gripper.load("2f85")))
    assert world.check_arm(np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])) is None
    # forearm folded back onto the base column: a self-collision, reported as such
    hit = world.check_arm(np.array([0.0, -1.5708, 2.9, 0.0, 0.0, 0.0]))
    assert hit is not None and hit.reason == "collision_self"


def test_example_cells_load() -> None:
    cell = load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")
    assert cell.robot_model == "ur5e" and cell.tool.kind == "parallel" and cell.bin is not None
    assert cell.tool.stroke_m == pytest.approx(0.085)
    assert np.all(cell.motion.joint_velocity <= np.deg2rad(180) + 1e-9)
    names = [b.name for b in cell.static_boxes]
    assert "bin/floor" in names and "table" in names
    conveyor = load_cell(EXAMPLES / "ur10e_conveyor_suction.yaml")
    assert conveyor.tool.kind == "suction" and conveyor.bin is None and len(conveyor.places) == 2
    assert conveyor.world_from_camera is None


def _minimal() -> dict:
    return {
        "robot": {"model": "ur5e"},
        "gripper": {"model": "2f85"},
        "place": [{"world_from_tcp": {"xyz": [0.0, -0.4, 0.0], "rpy_deg": [180, 0, 0]}}],
    }


@pytest.mark.parametrize(
    ("patch", "path"),
    [
        (lambda d: d["robot"].pop("model"), "robot.model"),
        (lambda d: d["robot"].update(model="ur99"), "robot.model"),
        (lambda d: d["robot"].update(home=[0, 0, 9, 0, 0, 0]), "robot.home"),
        (lambda d: d["gripper"].update(model="3f200"), "gripper.model"),
        (lambda d: d.update(gripper={"model": "x", "kind": "parallel", "flange_to_tcp_m": 0.1}), "gripper.stroke_m"),
        (lambda d: d.update(bin={"pose": {"xyz": [0, 0, 0]}, "inner_size": [0.4, -0.3, 0.1]}), "bin.inner_size"),
        (
            lambda d: d["place"][0].update(world_from_tcp={"xyz": [0, 0], "rpy_deg": [0, 0, 0]}),
            "place[0].world_from_tcp",
        ),
        (lambda d: d.update(motion={"workspace": {"min": [0, 0, 0], "max": [0, 1, 1]}}), "motion.workspace"),
        (lambda d: d.update(colour="red"), "colour"),
        (
            lambda d: d.update(table={"pose": {"xyz": [0, 0, 0], "rpy_deg": [0, 0, 0], "scale": 2}, "size": [1, 1, 1]}),
            "table.pose",
        ),
    ],
)
def test_cell_errors_name_the_key(patch, path: str) -> None:  # type: ignore[no-untyped-def]
    data = _minimal()
    cell_from_dict(data)  # the minimal file is valid
    patch(data)
    with pytest.raises(CellConfigError) as info:
        cell_from_dict(data)
    assert info.value.path.startswith(path), (info.value.path, str(info.value))


def test_cell_file_errors(tmp_path: Path) -> None:
    with pytest.raises(CellConfigError, match="cannot read"):
        load_cell(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot: [unclosed\n", encoding="utf-8")
    with pytest.raises(CellConfigError, match="not valid YAML"):
        load_cell(bad)
    bad.write_text("- a\n- b\n", encoding="utf-8")
    with pytest.raises(CellConfigError, match="mapping"):
        load_cell(bad)
