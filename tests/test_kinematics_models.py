"""Robot and gripper descriptions: committed files regenerate byte-identically, load in MuJoCo and pinocchio
without warnings, and agree with the DH table; grippers load, round-trip YAML and build collision shapes."""

from __future__ import annotations

import warnings
from importlib import resources
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from normpos_grasp.errors import InputError, RobotModelError
from normpos_grasp.kinematics import ARM_LINKS, ROBOT_NAMES, Gripper, Robot, dh_forward_kinematics, ur_params
from normpos_grasp.kinematics.gripper import GRIPPER_NAMES
from normpos_grasp.robot_models.generate import render_all

ROOT = Path(str(resources.files("normpos_grasp.robot_models")))


def test_committed_files_match_the_generator() -> None:
    files = render_all()
    assert len(files) == 3 * len(ROBOT_NAMES) + len(GRIPPER_NAMES) + 2
    for rel, text in files.items():
        path = ROOT / rel
        assert path.is_file(), f"{rel} missing: run python -m normpos_grasp.robot_models.generate"
        assert path.read_bytes() == text.encode("utf-8"), f"{rel} differs from the generator"
    assert render_all() == files  # deterministic


def _mujoco_flange(model: mujoco.MjModel, data: mujoco.MjData, q: np.ndarray) -> np.ndarray:
    data.qpos[:6] = q
    mujoco.mj_kinematics(model, data)
    site = data.site("flange")
    pose = np.eye(4)
    pose[:3, :3] = site.xmat.reshape(3, 3)
    pose[:3, 3] = site.xpos
    return pose


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_model_loads_and_fk_agrees_everywhere(name: str) -> None:
    robot = Robot.load(name)
    folder = ROOT / name
    assert {p.name for p in folder.iterdir()} >= {f"{name}.xml", "scene.xml", "README.md"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mj = mujoco.MjModel.from_xml_path(str(folder / f"{name}.xml"))
        scene = mujoco.MjModel.from_xml_path(str(folder / "scene.xml"))
        pm = pin.buildModelFromMJCF(str(folder / f"{name}.xml"))
    assert mj.nq == 6 and scene.nq == 6 and pm.nq == 6
    md, pd = mujoco.MjData(mj), pm.createData()
    rng = np.random.default_rng(7)
    lower, upper = robot.joint_limits
    for q in rng.uniform(np.maximum(lower, -7), np.minimum(upper, 7), size=(25, 6)):
        ref = dh_forward_kinematics(robot.params, q)
        pin.framesForwardKinematics(pm, pd, q)
        np.testing.assert_allclose(pd.oMf[pm.getFrameId("flange")].homogeneous, ref, atol=1e-9)
        np.testing.assert_allclose(_mujoco_flange(mj, md, q), ref, atol=1e-9)
        np.testing.assert_allclose(robot.fk(q), ref, atol=1e-9)
        np.testing.assert_allclose(robot.fk_batch(q[None])[0], ref, atol=1e-12)
        poses = robot.link_poses(q)
        for link in ARM_LINKS:
            body = md.body(link)
            np.testing.assert_allclose(poses[link][:3, 3], body.xpos, atol=1e-9)
            np.testing.assert_allclose(poses[link][:3, :3], body.xmat.reshape(3, 3), atol=1e-9)


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_scene_steps_without_warnings_or_self_contact(name: str) -> None:
    model = mujoco.MjModel.from_xml_path(str(ROOT / name / "scene.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    for _ in range(300):
        mujoco.mj_step(model, data)
    assert all(w.number == 0 for w in data.warning)
    assert data.ncon == 0
    assert np.abs(data.qpos - model.key_qpos[0]).max() < 0.05  # the servos hold the home pose under gravity


@pytest.mark.parametrize("name", ROBOT_NAMES)
def test_collision_geometry_matches_the_mjcf(name: str) -> None:
    robot = Robot.load(name)
    shapes = robot.collision_geometry
    assert {s.link for s in shapes} == set(ARM_LINKS)
    model = robot.mujoco_model()
    data = mujoco.MjData(model)
    q = np.array([0.4, -1.1, 1.3, -1.9, -1.4, 0.6])
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    poses = robot.link_poses(q)
    assert model.ngeom == len(shapes)
    for i, shape in enumerate(shapes):  # generator writes geoms in the same order
        world = poses[shape.link] @ shape.link_from_shape
        np.testing.assert_allclose(world[:3, 3], data.geom_xpos[i], atol=1e-9)
        np.testing.assert_allclose(world[:3, 2], data.geom_xmat[i].reshape(3, 3)[:, 2], atol=1e-9)
        assert model.geom_size[i, 0] == pytest.approx(shape.size[0])
    # the UR5e reference sizes are those of the real arm (footprint 149 mm)
    if name == "ur5e":
        assert shapes[0].size[0] == pytest.approx(0.0745)


def test_unknown_robot_names_the_known_ones() -> None:
    with pytest.raises(RobotModelError, match="ur5e"):
        Robot.load("ur7")
    assert ur_params("UR10E").name == "ur10e"


@pytest.mark.parametrize("name", GRIPPER_NAMES)
def test_packaged_grippers(name: str, tmp_path: Path) -> None:
    g = Gripper.load(name)
    assert g.name == name
    assert g.flange_from_tcp[2, 3] > 0.05  # TCP out along the flange z axis
    shapes = g.collision_shapes()
    assert shapes and all(s.link == "tcp" for s in shapes)
    path = tmp_path / "g.yaml"
    import yaml

    path.write_text(yaml.safe_dump(g.to_dict()))
    again = Gripper.from_yaml(path)
    np.testing.assert_allclose(again.flange_from_tcp, g.flange_from_tcp, atol=1e-9)
    assert [s.size for s in again.collision_shapes()] == [s.size for s in shapes]
    if g.kind == "parallel":
        assert g.stroke_m in (0.085, 0.14)
        fingers = [s for s in g.collision_shapes(0.04) if s.kind == "box"][-2:]
        gap = abs(fingers[1].link_from_shape[0, 3] - fingers[0].link_from_shape[0, 3]) - fingers[0].size[0]
        assert gap == pytest.approx(0.04)
        with pytest.raises(InputError):
            g.collision_shapes(g.stroke_m + 0.01)
    else:
        assert g.cup_diameter_m > 0 and g.cup_stroke_m > 0


def test_gripper_mounting_offset_and_bad_yaml(tmp_path: Path) -> None:
    g = Gripper.load("2f85")
    offset = np.eye(4)
    offset[2, 3] = 0.02
    m = g.mounted(offset)
    assert m.flange_from_tcp[2, 3] == pytest.approx(g.flange_from_tcp[2, 3] + 0.02)
    adapter = [s for s in m.collision_shapes() if s.kind == "cylinder"][-1]
    assert adapter.size[1] == pytest.approx(0.02)
    assert adapter.link_from_shape[2, 3] == pytest.approx(-m.flange_from_tcp[2, 3] + 0.01)
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nkind: parallel\n")
    with pytest.raises(RobotModelError, match="bad.yaml"):
        Gripper.from_yaml(bad)
    with pytest.raises(RobotModelError, match="2f85"):
        Gripper.load("nope")
    s = Gripper.suction(cup_diameter_m=0.05, cup_stroke_m=0.02)
    assert s.cup_diameter_m == 0.05 and s.kind == "suction"


@pytest.mark.parametrize("gripper_name", GRIPPER_NAMES)
def test_arm_model_with_a_gripper_attached(gripper_name: str) -> None:
    robot = Robot.load("ur10e")
    tool = Gripper.load(gripper_name)
    offset = np.eye(4)
    offset[2, 3] = 0.015
    tool = tool.mounted(offset)
    model = robot.mujoco_model(tool, opening_m=None)
    data = mujoco.MjData(model)
    assert model.ngeom == len(robot.collision_geometry) + len(tool.collision_shapes())
    q = np.array([0.4, -1.1, 1.3, -1.9, -1.4, 0.6])
    data.qpos[:] = q
    mujoco.mj_forward(model, data)
    tcp = robot.fk(q) @ tool.flange_from_tcp
    np.testing.assert_allclose(data.site("tcp").xpos, tcp[:3, 3], atol=1e-9)
    assert data.ncon == 0
    mujoco.mj_resetDataKeyframe(model, data, 0)
    for _ in range(200):
        mujoco.mj_step(model, data)
    assert all(w.number == 0 for w in data.warning)
