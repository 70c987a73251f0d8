"""Cell YAML validation: every key at every level, every number's type, finiteness and range, caps within the
robot's rated limits, extrinsics that cannot be right, and YAML that cannot exhaust memory (issues 18, 20)."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from normpos_grasp.cell import cell_from_dict, load_cell
from normpos_grasp.errors import CellConfigError, ExtrinsicsError, RobotModelError, TemplateError
from normpos_grasp.io.yaml_safe import MAX_DEPTH, YamlError, load_yaml

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
ROOT = Path(__file__).resolve().parents[1]


def _cell() -> dict[str, Any]:
    """A valid UR5e bin cell (table top and bin floor at z = 0, camera 0.9 m above)."""
    return {
        "name": "t",
        "robot": {"model": "ur5e", "world_from_base": {"rpy_deg": [0, 0, 180]}},
        "gripper": {"model": "2f85", "kind": "parallel", "payload_kg": 2.0},
        "camera": {"world_from_camera": {"xyz": [0.5, 0.0, 0.9], "rpy_deg": [180, 0, -90]}},
        "table": {"pose": {"xyz": [0.3, 0.0, -0.025]}, "size": [1.4, 1.2, 0.05]},
        "bin": {"pose": {"xyz": [0.5, 0.0, 0.01]}, "inner_size": [0.4, 0.3, 0.15], "wall_m": 0.01},
        "fixtures": [{"name": "mast", "pose": {"xyz": [0.95, 0.0, 0.5]}, "size": [0.05, 0.05, 1.0]}],
        "place": [{"name": "tray", "world_from_tcp": {"xyz": [0.0, -0.45, 0.0], "rpy_deg": [180, 0, 0]}}],
        "motion": {
            "joint_velocity": 1.0,
            "joint_acceleration": 2.0,
            "tcp_speed_m_s": 0.25,
            "workspace": {"min": [-0.9, -0.9, -0.05], "max": [0.9, 0.9, 0.9]},
        },
        "planning": {"entry_clearance_m": 0.05},
    }


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    """A patch that sets the dotted `path` (list indices as numbers) to `value`."""

    def patch(d: dict[str, Any]) -> None:
        keys: list[Any] = [int(k) if k.isdigit() else k for k in path.split(".")]
        node: Any = d
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value

    return patch


_ZERO = [[0.0] * 4, [0.0] * 4, [0.0] * 4, [0.0, 0.0, 0.0, 1.0]]
_SCALED = [[1000.0, 0, 0, 0.5], [0, -1000.0, 0, 0.0], [0, 0, -1000.0, 0.9], [0, 0, 0, 1]]
_MIRROR = [[1.0, 0, 0, 0.5], [0, 1.0, 0, 0.0], [0, 0, -1.0, 0.9], [0, 0, 0, 1]]

# (patch, the path the error must name, a phrase the message must hold)
BAD: list[tuple[str, Callable[[dict[str, Any]], None], str, str]] = [
    ("nested typo", _set("motion.joint_velocty", 0.1), "motion.joint_velocty", "did you mean 'joint_velocity'"),
    (
        "acceleration 100000",
        _set("motion.joint_acceleration", 100000),
        "motion.joint_acceleration",
        "above the ceiling 40 rad/s^2",
    ),
    (
        "joint 5 too fast",
        _set("motion.joint_acceleration", [2] * 5 + [41]),
        "motion.joint_acceleration[5]",
        "wrist_3_joint",
    ),
    ("speed above rated", _set("motion.joint_velocity", 3.2), "motion.joint_velocity", "rated speed"),
    ("tcp speed 5 m/s", _set("motion.tcp_speed_m_s", 5.0), "motion.tcp_speed_m_s", "UR_TOOL_VELOCITY_MAX"),
    ("tcp accel 1000", _set("motion.tcp_acceleration_m_s2", 1000.0), "motion.tcp_acceleration_m_s2", "150"),
    ("acceleration as text", _set("motion.joint_acceleration", "1e5"), "motion.joint_acceleration", "1.0e3"),
    ("acceleration inf", _set("motion.joint_acceleration", float("inf")), "motion.joint_acceleration", "finite"),
    ("speed nan", _set("motion.joint_velocity", float("nan")), "motion.joint_velocity", "finite"),
    ("speed true", _set("motion.joint_velocity", True), "motion.joint_velocity", "expected a number"),
    ("speed negative", _set("motion.joint_velocity", -1.0), "motion.joint_velocity", "below"),
    ("workspace typo", _set("motion.workspace.maximum", [1, 1, 1]), "motion.workspace.maximum", "allowed here: min"),
    ("workspace in mm", _set("motion.workspace.max", [900, 900, 900]), "motion.workspace.max[0]", "millimetres"),
    ("pose typo", _set("bin.pose.rpy_degs", [0, 0, 0]), "bin.pose.rpy_degs", "did you mean 'rpy_deg'"),
    ("xyz in mm", _set("place.0.world_from_tcp.xyz", [0, -450, 0]), "place[0].world_from_tcp.xyz[1]", "millimetres"),
    ("rpy_deg 720", _set("bin.pose.rpy_deg", [0, 0, 720]), "bin.pose.rpy_deg[2]", "outside"),
    ("bin typo", _set("bin.wall", 0.01), "bin.wall", "wall_m"),
    ("bin wall 1 m", _set("bin.wall_m", 1.0), "bin.wall_m", "outside"),
    ("place typo", _set("place.0.approach", 0.1), "place[0].approach", "approach_m"),
    ("place name list", _set("place.0.name", ["a"]), "place[0].name", "text"),
    ("planning typo", _set("planning.lift", 0.1), "planning.lift", "lift_m"),
    ("fixture typo", _set("fixtures.0.colour", "red"), "fixtures[0].colour", "allowed here: name, pose, size"),
    ("table name", _set("table.name", "bench"), "table.name", "allowed here: pose, size"),
    ("robot typo", _set("robot.homee", [0] * 6), "robot.homee", "did you mean 'home'"),
    ("serial list", _set("robot.serial_number", [1, 2]), "robot.serial_number", "text"),
    ("gripper typo", _set("gripper.payload", 1.0), "gripper.payload", "allowed here"),
    ("payload above rated", _set("gripper.payload_kg", 50.0), "gripper.payload_kg", "rated payload 5"),
    ("gripper model number", _set("gripper.model", 85), "gripper.model", "text"),
    (
        "suction with a stroke",
        _set("gripper", {"model": "s", "kind": "suction", "flange_to_tcp_m": 0.1, "stroke_m": 0.05}),
        "gripper.stroke_m",
        "cup_diameter_m",
    ),
    ("camera typo", _set("camera.world_from_cam", _MIRROR), "camera.world_from_cam", "world_from_camera"),
    ("from_scene text", _set("camera", {"from_scene": "yes"}), "camera.from_scene", "true or false"),
    ("camera both", _set("camera.from_scene", True), "camera", "not both"),
    ("zero rotation", _set("camera.world_from_camera", _ZERO), "camera.world_from_camera", "= 1 (tolerance"),
    ("rotation x1000", _set("camera.world_from_camera", _SCALED), "camera.world_from_camera", "not a rotation"),
    ("reflection", _set("camera.world_from_camera", _MIRROR), "camera.world_from_camera", "determinant -1"),
    (
        "camera under the table",
        _set("camera.world_from_camera", {"xyz": [0.5, 0.0, -0.6], "rpy_deg": [0, 0, 0]}),
        "camera.world_from_camera",
        "under the floor",
    ),
    (
        "camera 800 m away",
        _set("camera.world_from_camera", [[1, 0, 0, 500.0], [0, -1, 0, 0], [0, 0, -1, 9.0], [0, 0, 0, 1]]),
        "camera.world_from_camera[0][3]",
        "millimetres",
    ),
    (
        "camera inside the workspace",
        _set("motion.workspace.max", [0.9, 0.9, 1.2]),
        "camera.world_from_camera",
        "inside motion.workspace",
    ),
    ("base under floor_z", _set("floor_z", 0.5), "robot.world_from_base", "floor_z"),
    ("floor_z text", _set("floor_z", "low"), "floor_z", "number"),
    ("name mapping", _set("name", {"a": 1}), "name", "text"),
    ("templates number", _set("templates", 3), "templates", "text"),
    ("top-level typo", _set("motions", {}), "motions", "did you mean 'motion'"),
]


@pytest.mark.parametrize(("case", "patch", "path", "phrase"), BAD, ids=[b[0] for b in BAD])
def test_bad_cells_name_the_key(case: str, patch: Callable[[dict[str, Any]], None], path: str, phrase: str) -> None:
    data = _cell()
    cell_from_dict(copy.deepcopy(data))  # the unpatched cell is valid
    patch(data)
    with pytest.raises(CellConfigError) as info:
        cell_from_dict(data)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(path) or info.value.path.startswith(path), (case, message)
    assert phrase in message, (case, message)


def test_valid_cell_keeps_every_value() -> None:
    data = _cell()
    data["robot"]["serial_number"] = 20235501234
    data["motion"]["joint_velocity"] = [1.0, 1.1, 1.2, 1.3, 1.4, 3.14]
    data["motion"]["joint_acceleration"] = 40.0
    data["motion"]["tcp_acceleration_m_s2"] = 1.5
    data["floor_z"] = -0.8
    cell = cell_from_dict(data)
    assert cell.robot_serial == "20235501234" and cell.floor_z == -0.8
    assert np.allclose(cell.motion.joint_velocity, [1.0, 1.1, 1.2, 1.3, 1.4, 3.14])
    assert np.all(cell.motion.joint_acceleration == 40.0) and cell.motion.tcp_acceleration_m_s2 == 1.5
    assert cell.camera_floor_z == pytest.approx(0.0)  # the table top, above the floor
    assert cell.world_from_camera is not None and cell.world_from_camera[2, 3] == pytest.approx(0.9)


def test_scalar_speed_cap_names_the_slowest_rated_joint() -> None:
    data = _cell()
    data["robot"]["model"] = "ur10e"
    data["motion"]["joint_velocity"] = 2.5  # UR10e base and shoulder are rated 120 deg/s = 2.094 rad/s
    with pytest.raises(
        CellConfigError, match=r"shoulder_pan_joint.s ceiling 2.094 rad/s .*one number caps every joint; give 6"
    ):
        cell_from_dict(data)
    data["motion"]["joint_velocity"] = [2.0, 2.0, 3.0, 3.1, 3.1, 3.1]
    assert cell_from_dict(data).motion.joint_velocity[2] == 3.0


def test_check_camera_against_the_cell() -> None:
    cell = cell_from_dict(_cell())
    below = np.eye(4)
    below[:3, 3] = [0.5, 0.0, -0.3]
    with pytest.raises(ExtrinsicsError, match="under the floor") as info:
        cell.check_camera(below)
    assert info.value.measured == pytest.approx(-0.3)
    above = below.copy()
    above[2, 3] = 1.2
    assert np.allclose(cell.check_camera(above), above)  # above the workspace (max z 0.9)
    inside = below.copy()
    inside[2, 3] = 0.6
    with pytest.raises(ExtrinsicsError, match="inside motion.workspace"):
        cell.check_camera(inside)
    data = _cell()
    del data["motion"]["workspace"]  # no workspace given: the default box does not judge cameras
    assert np.allclose(cell_from_dict(data).check_camera(inside), inside)


def test_example_cells_are_valid() -> None:
    names = sorted(p.name for p in EXAMPLES.glob("*.yaml"))  # every example cell, new ones included
    assert {"ur5e_bin_parallel.yaml", "ur10e_conveyor_suction.yaml", "ur5e_bin_suction.yaml"} <= set(names)
    for name in names:
        cell = load_cell(EXAMPLES / name)
        assert cell.motion.joint_acceleration.max() <= 40.0


# ------------------------------------------------------------------------------------------------------ YAML


def _alias_bomb(levels: int = 9) -> str:
    """A cell whose `name` expands to 9**levels strings (the issue's 1.3 kB file; > 24 GB as text)."""
    lines = ['l0: &l0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, levels + 1)]
    lines += [f"name: *l{levels}", "robot: {model: ur5e}", "gripper: {model: 2f85}"]
    lines += ["place: [{world_from_tcp: {xyz: [0, -0.4, 0], rpy_deg: [180, 0, 0]}}]"]
    lines += ["# " + "padding to the size of the issue's file " * 12]
    return "\n".join(lines) + "\n"


def test_alias_bomb_is_refused_quickly_under_a_memory_cap(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(_alias_bomb(), encoding="utf-8")
    assert 1000 < bomb.stat().st_size < 1600
    script = (
        "import resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))\n"  # 2 GiB of address space
        "from normpos_grasp.cell import load_cell\n"
        "from normpos_grasp.errors import CellConfigError\n"
        "try:\n"
        "    cell = load_cell(sys.argv[1])\n"
        "    print('loaded', len(str(cell.name)))\n"
        "except CellConfigError as exc:\n"
        "    print('refused:', exc)\n"
    )
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    t0 = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", script, str(bomb)], capture_output=True, text=True, timeout=120, env=env, cwd=ROOT
    )
    elapsed = time.perf_counter() - t0
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout.strip()
    assert out.startswith(f"refused: {bomb}:1:5: anchor &l0 refused"), out
    assert "\n" not in out and elapsed < 60


@pytest.mark.parametrize(
    ("text", "where", "phrase"),
    [
        ("robot: {model: ur5e\ngripper: {model: 2f85}\n", ":2:8:", "not valid YAML"),
        ("robot:\n  model: ur5e\n   gripper: x\n", ":3:", "not valid YAML"),
        ("motion:\n  joint_velocity: 0.1\n  joint_velocity: 3.0\n", ":3:3:", "duplicate key 'joint_velocity'"),
        ("base: &b {model: ur5e}\nrobot: *b\n", ":1:7:", "anchor &b refused"),
        ("robot:\n  <<: {model: ur5e}\n", ":2:3:", "merge key '<<' refused"),
        ("a: !!python/object/apply:os.system [ls]\n", ":1:4:", "could not determine a constructor"),
        ("[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1) + "\n", ":1:", "nested deeper than"),
    ],
)
def test_yaml_problems_are_one_line_with_file_line_col(tmp_path: Path, text: str, where: str, phrase: str) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(CellConfigError) as info:
        load_cell(path)
    message = str(info.value)
    assert message.startswith(f"{path}{where}") and phrase in message and "\n" not in message, message


def test_yaml_files_that_are_not_text(tmp_path: Path) -> None:
    latin = tmp_path / "latin.yaml"
    latin.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(CellConfigError, match="not UTF-8"):
        load_cell(latin)
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (1 << 20) + "\n", encoding="utf-8")
    with pytest.raises(CellConfigError, match="more than the 1048576"):
        load_cell(big)
    with pytest.raises(YamlError, match=r"<text>:2:1: not valid YAML: expected .,. or .\]."):
        load_yaml("a: [1\n", "<text>")
    assert load_yaml("a: {b: [1, 2.5, x]}\n") == {"a": {"b": [1, 2.5, "x"]}}


def test_gripper_and_template_yaml_refuse_aliases(tmp_path: Path) -> None:
    from normpos_grasp.kinematics.gripper import Gripper
    from normpos_grasp.templates.library import load_template

    gripper = tmp_path / "g.yaml"
    gripper.write_text("name: &n x\nkind: *n\n", encoding="utf-8")
    with pytest.raises(RobotModelError, match=r"g.yaml:1:7: anchor &n refused"):
        Gripper.from_yaml(gripper)
    folder = tmp_path / "tpl"
    folder.mkdir()
    (folder / "template.yaml").write_text(_alias_bomb(), encoding="utf-8")
    with pytest.raises(TemplateError, match=r"template.yaml:1:5: anchor &l0 refused"):
        load_template(folder)


# ------------------------------------------------------------------------------------------------------ CLI


def test_cli_bad_cell_is_one_line_exit_2_and_writes_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from normpos_grasp.cli.main import main

    cases = {
        "typo.yaml": "robot: {model: ur5e}\ngripper: {model: 2f85}\nmotion: {joint_velocty: 0.1}\n"
        "place: [{world_from_tcp: {xyz: [0, -0.4, 0], rpy_deg: [180, 0, 0]}}]\n",
        "accel.yaml": "robot: {model: ur5e}\ngripper: {model: 2f85}\nmotion: {joint_acceleration: 100000}\n"
        "place: [{world_from_tcp: {xyz: [0, -0.4, 0], rpy_deg: [180, 0, 0]}}]\n",
        "bomb.yaml": _alias_bomb(),
        "syntax.yaml": "robot: {model: ur5e\n",
    }
    expected = {
        "typo.yaml": "motion.joint_velocty: unknown key; did you mean 'joint_velocity'?",
        "accel.yaml": "motion.joint_acceleration: 100000 rad/s^2 is above",
        "bomb.yaml": "bomb.yaml:1:5: anchor &l0 refused",
        "syntax.yaml": "syntax.yaml:2:1: not valid YAML",
    }
    for name, text in cases.items():
        cell = tmp_path / name
        cell.write_text(text, encoding="utf-8")
        out = tmp_path / f"{name}.plan.json"
        code = main(["plan", str(tmp_path), "--cell", str(cell), "--im-id", "0", "--out", str(out)])
        err = capsys.readouterr().err.strip()
        assert code == 2, (name, err)
        assert len(err.splitlines()) == 1 and expected[name] in err, (name, err)
        assert not out.exists()
