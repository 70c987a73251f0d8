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
from normpos_grasp.errors import SafetyViolation
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


def _samples(home: np.ndarray, q1: np.ndarray, duration: float, dip: float, n: int = 61) -> tuple[np.ndarray, ...]:
    """A cosine-profile trajectory home -> q1 over `duration` s, with the shoulder lowered by `dip` rad mid-way
    (zero at both ends, so the waypoints stay where they are)."""
    t = np.linspace(0.0, duration, n)
    s = (1 - np.cos(np.pi * t / duration)) / 2
    q = home + np.outer(s, q1 - home)
    q[:, 1] += dip * np.sin(np.pi * t / duration) ** 2
    return t, q


def test_no_plan_whose_samples_leave_the_workspace_or_the_rated_caps_is_accepted(cell_file: Path) -> None:
    """Seeded plans whose waypoints lie inside the cell but whose timed samples may dip under the workspace floor
    or run faster than the caps: every plan the judge accepts is re-checked sample by sample with an independent
    forward kinematics (the reference controller's DH chain) against the cell's box, the cell's caps and the
    UR5e's rated joint speeds."""
    from normpos_grasp.execution import execute_plan
    from normpos_grasp.kinematics.ur_params import ur_params
    from normpos_grasp.sim.rtde_reference.robot import frames

    cell = load_cell(cell_file)
    limits = SafetyLimits.from_cell(cell)
    home = np.asarray(cell.home_q, dtype=np.float64)
    params = ur_params(cell.robot_model)
    rated = np.asarray(params.velocity_limit)
    world_from_base = np.asarray(cell.world_from_base)
    tool = np.asarray(cell.tool.flange_from_tcp)
    rng = np.random.default_rng(18)
    accepted = refused_samples_only = 0
    for _ in range(60):
        q1 = home + rng.uniform(-0.4, 0.4, 6) * np.array([1, 0.3, 0.3, 0.5, 0.5, 1])
        t, q = _samples(home, q1, float(rng.uniform(0.4, 3.0)), float(rng.choice([0.0, rng.uniform(0.0, 0.9)])))
        plan = _plan(cell_file, [home, q1])
        plan["trajectory"] = {"samples": [{"t": float(a), "q": b.tolist()} for a, b in zip(t, q, strict=True)]}
        try:
            execute_plan(None, plan, limits)
        except SafetyViolation as exc:
            if "trajectory" in str(exc):
                refused_samples_only += 1
            continue
        accepted += 1
        tcp = np.array([(world_from_base @ frames(params, qi)[-1] @ tool)[:3, 3] for qi in q])
        assert np.all(tcp >= limits.workspace_min - 1e-9) and np.all(tcp <= limits.workspace_max + 1e-9)
        qd = np.diff(q, axis=0) / np.diff(t)[:, None]
        assert np.all(np.abs(qd) <= np.minimum(rated, limits.max_joint_speed) * (1 + 1e-6))
        qdd = np.diff(qd, axis=0) / np.diff(t)[1:, None]
        assert np.all(np.abs(qdd) <= limits.max_joint_accel * (1 + 1e-6) + 1e-9)
    assert accepted >= 10 and refused_samples_only >= 10, (accepted, refused_samples_only)


def test_execute_refuses_a_trajectory_that_dips_under_the_table(cell_file: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    """Both waypoints are inside the workspace; only the timed samples between them leave it."""
    cell = load_cell(cell_file)
    home = np.asarray(cell.home_q, dtype=np.float64)
    limits = SafetyLimits.from_cell(cell)
    q1 = home + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0])
    dip = next(
        d
        for d in np.arange(0.05, 1.5, 0.05)
        if (limits.box_from_base @ limits.base_from_tcp(home + [0, d, 0, 0, 0, 0]))[2, 3]
        < limits.workspace_min[2] - 0.02
    )
    t, q = _samples(home, q1, 4.0, float(dip) + 0.1)
    plan = _plan(cell_file, [home, q1])
    plan["trajectory"] = {"samples": [{"t": float(a), "q": b.tolist()} for a, b in zip(t, q, strict=True)]}
    code, err = _execute(capsys, str(_write(tmp_path, plan)), "--execute")
    assert code == 2 and "trajectory" in err and "workspace" in err, err


def test_a_dual_tool_plan_is_judged_with_its_tool_and_the_callers_caps() -> None:
    """On a dual-tool flange the loop mounts the plan's tool (its TCP judges the workspace box) and keeps every cap
    it was given: limits tightened by the caller are never replaced by the cell's."""
    from dataclasses import replace
    from types import SimpleNamespace

    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.loop import plan_limits

    cell = resolve_cell("ur5e_bin_dual")
    slow = replace(SafetyLimits.from_cell(cell), max_joint_speed=np.full(6, 0.5), max_joint_accel=np.full(6, 1.0))
    for tool in cell.tools:
        judged = plan_limits(cell, SimpleNamespace(tool=SimpleNamespace(name=tool.name)), slow)  # type: ignore[arg-type]
        assert np.array_equal(judged.flange_from_tcp, tool.flange_from_tcp)
        assert np.all(judged.max_joint_speed == 0.5) and np.all(judged.max_joint_accel == 1.0)
        assert np.array_equal(judged.workspace_min, slow.workspace_min) and judged.cell == slow.cell
    assert not np.array_equal(cell.tools[0].flange_from_tcp, cell.tools[1].flange_from_tcp)
