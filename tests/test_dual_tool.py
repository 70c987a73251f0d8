"""The dual-tool example cell (issue 17 item 2): a 2F-85 and a 30 mm suction cup on one flange, the tool chosen per
part. Parsing `gripper:` as a list, the idle tool's body in each tool's collision model, the planner's choice, the
physics hand of the chosen tool, and the outputs execution switches."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell import resolve_cell
from normpos_grasp.cell.config import cell_from_dict
from normpos_grasp.collision.world import CollisionWorld
from normpos_grasp.errors import CellConfigError, InputError, SafetyViolation
from normpos_grasp.geometry import make_pose
from normpos_grasp.io.yaml_safe import load_yaml_file
from normpos_grasp.planning import plan_pick
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.records.tool import IDLE_PREFIX, own_shapes
from normpos_grasp.sim.parts import default_part_library

CELL_FILE = Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_bin_dual.yaml"
DUAL = resolve_cell("ur5e_bin_dual")
JAWS, CUP = DUAL.tools


def _data() -> dict[str, Any]:
    data = load_yaml_file(CELL_FILE)
    assert isinstance(data, dict)
    data.pop("templates")
    return data


def _fit(template: Template, xyz: tuple[float, float, float]) -> TemplateFit:
    return TemplateFit(template, make_pose(np.eye(3), list(xyz)), 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=1)


def test_the_dual_cell_has_both_tools_each_with_the_others_body() -> None:
    assert [t.name for t in DUAL.tools] == ["2f85", "suction_30"] and DUAL.tool is JAWS
    assert JAWS.kind == "parallel" and CUP.kind == "suction" and CUP.cup_diameter_m == pytest.approx(0.03)
    # the extended cup's lip 55 mm off the flange axis, 40 mm past the jaw tips (0.163 m from the flange)
    assert np.allclose(CUP.flange_from_tcp[:3, 3], [0.0, 0.055, 0.203])
    assert {s.name for s in JAWS.shapes if s.name.startswith(IDLE_PREFIX)} == {
        "idle/suction_30/cup", "idle/suction_30/stem", "idle/suction_30/body"
    }  # fmt: skip
    idle_jaws = [s for s in CUP.shapes if s.name.startswith(IDLE_PREFIX)]
    assert len(idle_jaws) == len(own_shapes(JAWS)) and all(s.moves == 0 for s in idle_jaws)
    # the idle cup, seen from the jaws' TCP: drawn back 100 mm on its slide, the lip 47 mm above the jaws' TCP
    cup = next(s for s in JAWS.shapes if s.name == "idle/suction_30/cup")
    assert np.allclose(cup.tcp_from_shape[:3, 3], [0.0, 0.055, 0.053 - 0.10 - 0.005])
    # the idle jaws, seen from the cup's TCP: their tips 40 mm behind the extended lip
    tip = min(s.tcp_from_shape[2, 3] + s.size[2] / 2 for s in CUP.shapes if "finger" in s.name)
    assert tip == pytest.approx(-0.04)
    assert [d.kind for d in DUAL.gripper_drivers if d is not None] == ["io", "vacuum"]
    # plan.json's tool entry lists the idle body too
    assert any(c["name"].startswith(IDLE_PREFIX) for c in CUP.to_json(0.0)["collision"])
    # a one-tool cell has a 1-tuple
    parallel = resolve_cell("ur5e_bin_parallel")
    assert parallel.tools == (parallel.tool,) and parallel.gripper_drivers == (parallel.gripper_driver,)


@pytest.mark.parametrize(
    ("gripper", "path", "message"),
    [
        ([], "gripper", "a list of 1-2 mappings"),
        ("2f85", "gripper", "a list of 1-2 mappings"),
        ([{"model": "2f85"}, {"model": "2f85"}], "gripper[1].model", "given twice"),
        ([{"model": "2f85"}, "suction"], "gripper[1]", "expected a mapping"),
        ([{"model": "2f85"}, {"model": "x", "kind": "suction", "flange_to_tcp_m": 0.16, "stroke_m": 0.05}],
         "gripper[1].stroke_m", "unknown key"),
        ([{"model": "2f85"}, {"model": "2f140"}, {"model": "x", "kind": "suction", "flange_to_tcp_m": 0.2}],
         "gripper", "a list of 1-2 mappings"),
        ([{"model": "2f85", "driver": {"type": "vacuum"}}, {"model": "2f140"}], "gripper[0].driver", "suction"),
        ([{"model": "2f85", "retract_m": 0.05}], "gripper[0].retract_m", "beside another tool"),
        ([{"model": "2f85"}, {"model": "2f140", "retract_m": -0.01}], "gripper[1].retract_m", "."),
    ],
)  # fmt: skip
def test_bad_dual_grippers_are_refused_with_the_key(gripper: Any, path: str, message: str) -> None:
    data = _data()
    data["gripper"] = gripper
    with pytest.raises(CellConfigError, match=message) as refused:
        cell_from_dict(data, CELL_FILE.parent)
    assert str(refused.value).startswith(path)


def test_a_list_of_one_gripper_is_the_one_tool_cell() -> None:
    data = _data()
    data["gripper"] = [{"model": "2f85", "kind": "parallel"}]
    cell = cell_from_dict(data, CELL_FILE.parent)
    assert len(cell.tools) == 1 and not any(s.name.startswith(IDLE_PREFIX) for s in cell.tool.shapes)


def test_a_plate_too_wide_for_the_jaws_is_planned_with_the_cup() -> None:
    # 150 x 120 x 20 mm lying flat: both faces wider than the 85 mm stroke, the edges on the floor
    slab = Template("slab", "slab", trimesh.creation.box((0.15, 0.12, 0.02)), mass_kg=0.3, shape="box")
    fit = _fit(slab, (0.5, 0.0, 0.02))
    jaws_only = plan_pick([fit], [], DUAL.with_tool(JAWS))
    assert jaws_only.status == "no_feasible_grasp"
    plan = plan_pick([fit], [], DUAL)
    assert plan.status == "ok" and plan.chosen is not None
    assert plan.tool.name == "suction_30" and plan.chosen.candidate.scheme == "suction"
    entry = plan.to_json()["tool"]
    assert entry["name"] == "suction_30" and entry["type"] == "suction"
    assert np.allclose(entry["flange_from_tcp"], CUP.flange_from_tcp)


def test_a_sphere_no_cup_seals_on_is_planned_with_the_jaws() -> None:
    sphere = next(t for t in default_part_library() if t.name == "sphere")
    plan = plan_pick([_fit(sphere, (0.5, 0.0, 0.0325))], [], DUAL)
    assert plan.status == "ok" and plan.chosen is not None
    assert plan.tool.name == "2f85" and plan.chosen.candidate.scheme == "parallel"
    cup_only = plan_pick([_fit(sphere, (0.5, 0.0, 0.0325))], [], DUAL.with_tool(CUP))
    assert cup_only.status == "no_feasible_grasp"  # no patch of a 45 mm sphere takes a 30 mm cup


def test_the_idle_cup_is_in_the_jaws_collision_model() -> None:
    # a top-down pinch 55 mm from the bin's +y wall, the TCP 11 cm under the rim: the palm (37.5 mm half width)
    # clears it, the drawn-back idle cup beside the palm (40-70 mm off the jaw axis) lies in the wall when it is on
    # the wall's side
    wall = next(b for b in DUAL.static_boxes if b.name == "bin/wall_y+")
    inner_y = float(wall.world_from_box[1, 3] - wall.size[1] / 2)
    world = CollisionWorld()
    world.add_box(wall.name, wall.world_from_box, wall.size, "cell")
    down = np.diag([1.0, -1.0, -1.0])  # TCP z down, x along world +x: TCP y = world -y
    at = [0.5, inner_y - 0.055, 0.05]
    cup_away, cup_towards = make_pose(down, at), make_pose(down @ np.diag([-1.0, -1.0, 1.0]), at)
    world.set_tool(JAWS)
    world.update()
    assert world.check_tool(cup_away, 0.05) is None
    hit = world.check_tool(cup_towards, 0.05)
    assert hit is not None and hit.reason == "collision_cell"
    assert list(world.tool_box_hits(np.stack([cup_away, cup_towards]), np.array([0.05, 0.05]))) == [False, True]
    world.set_tool(replace(JAWS, shapes=own_shapes(JAWS)))  # the 2F-85 alone fits either way
    assert world.check_tool(cup_towards, 0.05) is None


def test_a_cube_by_the_wall_is_grasped_with_the_cup_away_from_it() -> None:
    cube = next(t for t in default_part_library() if t.name == "cube")
    wall = next(b for b in DUAL.static_boxes if b.name == "bin/wall_y+")
    y = float(wall.world_from_box[1, 3] - wall.size[1] / 2) - 0.055
    plan = plan_pick([_fit(cube, (0.5, y, 0.03))], [], DUAL)
    assert plan.status == "ok" and plan.chosen is not None and plan.tool.name == "2f85"
    # the pass that found it is on the plan: the turned copies carry '@turn' in their id, the first pass's do not
    assert plan.planning_pass == ("turned" if "@turn" in plan.chosen.candidate.grasp_id else "first")
    tcp = plan.chosen.world_from_tcp[2] if plan.chosen.world_from_tcp is not None else None
    assert tcp is not None
    cup_y = (tcp @ next(s for s in JAWS.shapes if s.name == "idle/suction_30/cup").tcp_from_shape)[1, 3]
    inner_y = float(wall.world_from_box[1, 3] - wall.size[1] / 2)
    assert cup_y + 0.015 < inner_y  # the idle cup (30 mm) clear of the wall: turned away from it, or along it


def test_the_physics_hand_is_the_chosen_tools_with_the_idle_body() -> None:
    from normpos_grasp.simulate.episode import gripper_spec, gripper_specs

    specs = gripper_specs(DUAL, "")
    assert specs["2f85"].kind == "parallel" and specs["suction_30"].kind == "suction"
    assert specs["suction_30"].cup_diameter_m == pytest.approx(0.03)
    # the cup's hand carries the idle 2F-85 (palm and both fingers), the jaws' the idle cup
    sizes = [size for _, size, _ in specs["suction_30"].body_shapes]
    assert (0.125, 0.075, 0.09) in sizes and sizes.count((0.02, 0.027, 0.062)) == 2
    assert (0.03, 0.03, 0.01) in [size for _, size, _ in specs["2f85"].body_shapes]
    with pytest.raises(InputError, match="leave --gripper out"):
        gripper_spec(DUAL, "2f140")


def test_execution_switches_to_the_chosen_tools_outputs_and_a_real_controller_is_refused() -> None:
    from types import SimpleNamespace

    from normpos_grasp.execution.safety import SafetyLimits
    from normpos_grasp.loop import tool_outputs_hook

    driver = SimpleNamespace(gripper=None, limits=SafetyLimits.from_cell(DUAL))
    hook = tool_outputs_hook(DUAL, driver)
    hook(SimpleNamespace(tool=CUP))  # the cup's vacuum (2) and release (3) outputs, its TCP judged
    assert (driver.gripper.close_output, driver.gripper.open_output, driver.gripper.grip_detect_input) == (2, 3, None)
    assert np.allclose(driver.limits.flange_from_tcp, CUP.flange_from_tcp)
    hook(SimpleNamespace(tool=JAWS))
    assert (driver.gripper.close_output, driver.gripper.open_output) == (0, 1)
    assert np.allclose(driver.limits.flange_from_tcp, JAWS.flange_from_tcp)
    with pytest.raises(InputError, match="no tool 'other'"):
        hook(SimpleNamespace(tool=replace(JAWS, name="other")))
    with pytest.raises(InputError, match="cannot switch to the tool a plan chose"):
        DUAL.refuse_dual_tool("the controller at 10.0.0.2")
    resolve_cell("ur5e_bin_parallel").refuse_dual_tool("the controller")  # one tool: nothing to refuse


@pytest.mark.slow  # 1.6 s in this file at load 1.8, 7.7 s at load 8 (alone it also loads the pipeline)
def test_the_dual_cell_clears_a_plate_in_simulate_with_the_chosen_tools_hand(monkeypatch: pytest.MonkeyPatch) -> None:
    """One plate in the bin, D435 noise at 320x240, ideal masks: planned with one of the two tools, replayed in
    physics with that tool's hand (jaws or cup, the idle body among its shapes), held, the bin cleared."""
    import normpos_grasp.simulate.episode as episode

    hands: list[Any] = []
    validate = episode.validate_grasp

    def spy(*args: Any, **kwargs: Any) -> Any:
        hands.append(args[4])
        return validate(*args, **kwargs)

    monkeypatch.setattr(episode, "validate_grasp", spy)
    config = episode.SimulationConfig(
        cell_path=str(CELL_FILE), segmenter="gt", parts=("plate",), parts_per_scene=1, resolution=(320, 240)
    )
    result = episode.run_scene(config, 0)
    assert [(p.part, p.success) for p in result.picks] == [("plate", True)], [(p.cause, p.reason) for p in result.picks]
    assert result.cleared and len(hands) == 1
    assert hands[0].kind == result.picks[0].scheme  # the hand of the tool the plan chose
    tool = next(t for t in DUAL.tools if t.kind == hands[0].kind)
    alone = episode.tool_spec(replace(tool, shapes=own_shapes(tool)))
    assert len(hands[0].body_shapes) > len(alone.body_shapes)  # with the idle tool's body


def test_execute_judges_a_cup_plan_with_the_cups_tcp_and_refuses_a_real_controller(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    from normpos_grasp.cli.main import main

    slab = Template("slab", "slab", trimesh.creation.box((0.15, 0.12, 0.02)), mass_kg=0.3, shape="box")
    plan = plan_pick([_fit(slab, (0.5, 0.0, 0.02))], [], DUAL)
    assert plan.tool.name == "suction_30"
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(plan.to_json()))
    # a real controller: one line, exit 2, nothing connected
    assert main(["execute", str(path), "--cell", str(CELL_FILE), "--execute", "--robot", "10.0.0.2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot switch to the tool a plan chose" in err[0]
    # judged with the cup's TCP mounted (the dry run passes); against the jaws' TCP the same plan is refused
    assert main(["execute", str(path), "--cell", str(CELL_FILE), "--robot", "sim"]) == 0
    assert "plan checked" in capsys.readouterr().out
    from normpos_grasp.execution.plan import check_plan, parse_plan
    from normpos_grasp.execution.safety import SafetyLimits

    with pytest.raises(SafetyViolation, match="not the tool mounted"):
        check_plan(parse_plan(plan.to_json()), SafetyLimits.from_cell(DUAL))
