"""Which grasp each simulated pick used and what produced it (`PickRecord.grasp_id`, `kind`, `plan_pass`, `relaxed`,
`predicted_success`): recorded from the plan the episode carried out, written to picks.csv, broken down per kind in
summary.json (adding up to the totals) with a predicted-against-observed calibration table."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import pytest

from normpos_grasp.errors import InputError
from normpos_grasp.planning import plan as plan_module
from normpos_grasp.simulate import episode
from normpos_grasp.simulate.batch import (
    CSV_COLUMNS,
    NO_GRASP,
    BatchResult,
    format_breakdown,
    summarise,
    write_results,
)
from normpos_grasp.simulate.episode import KINDS, PickRecord, SceneResult, SimulationConfig, grasp_kind

CELL = Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_bin_parallel.yaml"
NEW = ("grasp_id", "kind", "plan_pass", "relaxed", "predicted_success")


def test_the_kind_is_the_manipulation_then_the_relaxed_pass_then_the_planner_pass() -> None:
    assert grasp_kind("first", False, "") == "first"
    assert grasp_kind("leaned", False, "") == "leaned"
    assert grasp_kind("turned", False, "") == "turned"
    assert grasp_kind("leaned", True, "") == "relaxed"
    assert grasp_kind("first", True, "drag") == "drag"
    assert grasp_kind("leaned", False, "push") == "push"
    with pytest.raises(ValueError, match="not in"):
        grasp_kind("", False, "")  # a chosen grasp always comes from a planner pass
    with pytest.raises(ValueError, match="not in"):
        grasp_kind("first", False, "tilt")


def _pick(n: int, success: bool, kind: str, plan_pass: str, predicted: float, physics: str = "held") -> PickRecord:
    nan = float("nan")
    return PickRecord(
        0, n, success, "" if success else "physics_drop", "cube", "cube", "parallel", physics, "", 0.02, 0.1, 0.001,
        nan, nan, 3, 1, 1, 0, 0, 0, 1.0, 1.0, grasp_id=f"g{n}" if kind else "", kind=kind, plan_pass=plan_pass,
        relaxed=kind == "relaxed", predicted_success=predicted,
    )  # fmt: skip


def _batch(picks: tuple[PickRecord, ...]) -> BatchResult:
    return BatchResult(SimulationConfig(cell_path=str(CELL)), (SceneResult(0, len(picks), False, picks, 1),))


def test_the_breakdown_adds_up_and_the_calibration_bins_the_judged_grasps() -> None:
    nan = float("nan")
    picks = (
        _pick(0, True, "first", "first", 1.0),
        _pick(1, False, "first", "first", 1.0, "slip"),
        _pick(2, True, "leaned", "leaned", 0.8),
        _pick(3, True, "drag", "leaned", 0.5),
        _pick(4, False, "relaxed", "first", 0.5, "drop"),
        _pick(5, False, "first", "first", 0.8, ""),  # the chosen instance covered no part: no physics
        _pick(6, False, "", "", nan, ""),  # a give-up
    )
    s = summarise(_batch(picks))
    kinds = s["by_kind"]
    assert list(kinds) == ["first", "leaned", "relaxed", "drag", NO_GRASP]  # KINDS order, populated only
    assert kinds["first"] == {"picks": 3, "held": 1, "held_pct": 33.33}
    assert kinds["drag"] == {"picks": 1, "held": 1, "held_pct": 100.0}
    assert sum(r["picks"] for r in kinds.values()) == s["picks_attempted"] == 7
    assert sum(r["held"] for r in kinds.values()) == s["picks_succeeded"] == 3
    passes = s["by_plan_pass"]
    assert passes["leaned"] == {"picks": 2, "held": 2, "held_pct": 100.0}  # the dragged part's grasp was leaned
    assert sum(r["picks"] for r in passes.values()) == 7
    rows = {(r["low"], r["high"]): r for r in s["calibration"]}
    assert list(rows) == [(0.5, 0.6), (0.8, 0.9), (0.9, 1.0)]
    assert rows[(0.9, 1.0)] == {"low": 0.9, "high": 1.0, "picks": 2, "held": 1, "predicted": 1.0, "observed": 0.5}
    assert rows[(0.8, 0.9)]["picks"] == 1  # pick 5 (no physics) is not in the calibration
    assert sum(r["picks"] for r in s["calibration"]) == 5
    text = format_breakdown(s)
    assert "leaned" in text and "0.9-1.0" in text and "33.3" in text
    with pytest.raises(InputError, match="kind 'tilt'"):
        summarise(_batch((_pick(0, True, "tilt", "first", 1.0),)))


@pytest.mark.slow
def test_a_simulated_pick_records_the_grasp_its_plan_chose(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A tiny bin (2 parts, ideal masks, 320x240) run in this process with the planner spied on: every pick's grasp
    is the chosen grasp of a plan the episode made, with that plan's pass and predicted success."""
    plans: list[tuple[Any, Any]] = []
    real = plan_module.plan_pick

    def spy(
        fits: Any, normpositions: Any, cell: Any, options: Any = None, start_q: Any = None, uncovered: Any = None
    ) -> Any:
        plan = real(fits, normpositions, cell, options, start_q, uncovered)
        plans.append((plan, options))
        return plan

    monkeypatch.setattr(plan_module, "plan_pick", spy)
    config = SimulationConfig(
        cell_path=str(CELL), segmenter="gt", parts=("cube", "bar"), parts_per_scene=2, resolution=(320, 240), seed=3
    )
    result = episode.run_scene(config, 0)
    assert result.picks and plans
    chosen = {p.chosen.candidate.grasp_id: (p, o) for p, o in plans if p.status == "ok" and p.chosen is not None}
    with_grasp = [p for p in result.picks if p.grasp_id]
    assert with_grasp, [(p.cause, p.reason) for p in result.picks]
    for pick in result.picks:
        if not pick.grasp_id:
            assert pick.kind == pick.plan_pass == "" and math.isnan(pick.predicted_success)
            assert pick.cause == "no_feasible_grasp" or not pick.physics
            continue
        assert pick.grasp_id in chosen, (pick.grasp_id, sorted(chosen))
        plan, options = chosen[pick.grasp_id]
        assert pick.plan_pass == plan.planning_pass and pick.plan_pass in plan_module.PLANNING_PASSES
        assert pick.kind in KINDS
        assert pick.template == plan.chosen.candidate.template
        assert pick.predicted_success == pytest.approx(plan_module.predicted_success(plan, options))
        assert 0.0 < pick.predicted_success <= 1.0  # the evaluation refuses grasps the mechanics say will not hold
    summary = write_results(BatchResult(config, (result,)), tmp_path)
    rows = list(csv.DictReader((tmp_path / "picks.csv").open(encoding="utf-8")))
    assert tuple(rows[0]) == CSV_COLUMNS and CSV_COLUMNS[-len(NEW) :] == NEW
    for row, pick in zip(rows, result.picks, strict=True):
        assert row["grasp_id"] == pick.grasp_id and row["kind"] == pick.kind and row["plan_pass"] == pick.plan_pass
        assert row["relaxed"] == ("1" if pick.relaxed else "0")
        assert row["predicted_success"] == ("" if not pick.grasp_id else f"{pick.predicted_success:.6f}")
    assert sum(r["picks"] for r in summary["by_kind"].values()) == summary["picks_attempted"] == len(rows)
    assert sum(r["held"] for r in summary["by_kind"].values()) == summary["picks_succeeded"]
    judged = [p for p in result.picks if p.physics]
    assert sum(r["picks"] for r in summary["calibration"]) == len(judged)
    page = (tmp_path / "failures.html").read_text(encoding="utf-8")
    assert "Picks by grasp kind" in page and "Predicted against observed" in page
