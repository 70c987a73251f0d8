"""`execute` always has a judge: the cell the plan was made in (or --cell), whose workspace, mounted tool and caps
every waypoint and sample must respect; a plan with no cell and no explicit workspace is refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from normpos_grasp.cell import load_cell
from normpos_grasp.cli.main import main
from normpos_grasp.execution import SafetyLimits

ROOT = Path(__file__).resolve().parents[1]
CELL_YAML = ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml"


@pytest.fixture()
def cell_file(tmp_path: Path) -> Path:
    out = tmp_path / "cell" / "ur5e_bin_parallel.yaml"
    shutil.copytree(CELL_YAML.parent, out.parent)
    return out


def _plan(cell_path: Path, qs: list[np.ndarray], tool: np.ndarray | None = None, record: bool = True) -> dict:
    cell = load_cell(cell_path)
    plan: dict = {
        "status": "ok",
        "robot": cell.robot_model,
        "world_from_base": np.asarray(cell.world_from_base).tolist(),
        "tool": {"flange_from_tcp": np.asarray(cell.tool.flange_from_tcp if tool is None else tool).tolist()},
        "joint_waypoints": [{"name": f"w{i}", "q": np.asarray(q).tolist()} for i, q in enumerate(qs)],
    }
    if record:
        plan["cell"] = cell.record()
    return plan


def _write(tmp_path: Path, plan: dict) -> Path:
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(plan))
    return path


def _execute(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    code = main(["execute", *argv, "--robot", "sim"])
    return code, capsys.readouterr().err.strip()


def _below_the_workspace(cell_path: Path) -> np.ndarray:
    """Joints (within limits) that put the cell's TCP under its workspace floor: the shoulder lowered step by step."""
    cell = load_cell(cell_path)
    limits = SafetyLimits.from_cell(cell)
    world_from_tcp = limits.box_from_base @ limits.base_from_tcp(np.asarray(cell.home_q))
    q = np.asarray(cell.home_q, dtype=np.float64).copy()
    for _ in range(200):
        q[1] += 0.02
        world_from_tcp = limits.box_from_base @ limits.base_from_tcp(q)
        if world_from_tcp[2, 3] < limits.workspace_min[2] - 0.05:
            return q
    raise AssertionError(f"no shoulder angle puts the TCP under the workspace (last z {world_from_tcp[2, 3]:.3f} m)")


def test_the_recorded_cell_judges_without_flags(cell_file: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    home = np.asarray(load_cell(cell_file).home_q)
    ok = _write(tmp_path, _plan(cell_file, [home, home + 0.05]))
    code, err = _execute(capsys, str(ok))
    assert code == 0 and err == ""
    bad = _write(tmp_path, _plan(cell_file, [home, _below_the_workspace(cell_file)]))
    code, err = _execute(capsys, str(bad))
    assert code == 2 and "workspace" in err and len(err.splitlines()) == 1


def test_no_cell_and_no_workspace_is_refused(cell_file: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    home = np.asarray(load_cell(cell_file).home_q)
    plan = _write(tmp_path, _plan(cell_file, [home, home + 0.05], record=False))
    code, err = _execute(capsys, str(plan))
    assert code == 2 and "no cell to judge" in err and "--cell" in err
    code, err = _execute(capsys, str(plan), "--cell", str(cell_file))  # the flag it names works
    assert code == 0
    code, err = _execute(capsys, str(plan), "--cell", "ur5e_bin_parallel")  # a packaged cell name too
    assert code == 0


def test_the_plan_cannot_swap_the_mounted_tool(cell_file: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    home = np.asarray(load_cell(cell_file).home_q)
    plan = _write(tmp_path, _plan(cell_file, [home, home + 0.05], tool=np.eye(4)))  # checked at the flange
    code, err = _execute(capsys, str(plan))
    assert code == 2 and "not the tool mounted" in err


def test_a_changed_cell_file_is_not_trusted(cell_file: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    home = np.asarray(load_cell(cell_file).home_q)
    plan = _write(tmp_path, _plan(cell_file, [home, home + 0.05]))
    cell_file.write_text(cell_file.read_text() + "\n# edited after planning\n")
    code, err = _execute(capsys, str(plan))
    assert code == 2 and "changed since the plan was made" in err
    cell_file.unlink()
    code, err = _execute(capsys, str(plan))
    assert code == 2 and "not here" in err


def test_a_plan_for_another_arm_than_the_cell_is_refused(cell_file: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    home = np.asarray(load_cell(cell_file).home_q)
    plan = _plan(cell_file, [home, home + 0.05])
    plan["robot"] = "ur10e"
    code, err = _execute(capsys, str(_write(tmp_path, plan)))
    assert code == 2 and "ur10e" in err and "ur5e" in err
