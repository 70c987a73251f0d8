"""Several bins per cell (issue 19 item 6): `bins:` in the cell YAML and its validation, every bin's walls in the
planner's world, a part of bin B planned with bin B's entry, exit and places only, and a loop that empties the
bins in turn and stops when all are empty."""

from __future__ import annotations

import copy
import logging
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
import yaml

from normpos_grasp.cell import resolve_cell
from normpos_grasp.cell.config import cell_from_dict
from normpos_grasp.errors import CellConfigError
from normpos_grasp.execution import DriverOptions, SafetyLimits, SimDriver
from normpos_grasp.execution.plan import check_plan, parse_plan
from normpos_grasp.geometry import make_pose
from normpos_grasp.loop import SyntheticBinSource, run_cell_loop
from normpos_grasp.planning import plan_pick
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.sim.parts import default_part_library

CELL = resolve_cell("ur5e_two_bins")
PART = Template("box", "box", trimesh.creation.box((0.06, 0.04, 0.03)), shape="box")


def _data(name: str = "ur5e_two_bins") -> dict[str, Any]:
    with resources.as_file(resources.files("normpos_grasp.examples").joinpath("cells", f"{name}.yaml")) as p:
        data: dict[str, Any] = yaml.safe_load(p.read_text())
    data.pop("templates", None)
    return data


def _fit(xyz: list[float], instance: int) -> TemplateFit:
    return TemplateFit(PART, make_pose(np.eye(3), xyz), 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=instance)


def _tcp_z(plan: PickPlan, name: str) -> float:
    return float(next(w for w in plan.waypoints if w.name == name).world_from_tcp[2, 3])


def test_two_bin_example_cell() -> None:
    assert [b.name for b in CELL.bins] == ["left", "right"] and CELL.bin is CELL.bins[0]
    names = [b.name for b in CELL.static_boxes]
    for bin_name in ("left", "right"):  # every bin's floor and walls are static boxes of the cell
        assert all(f"bin/{bin_name}/{part}" in names for part in ("floor", "wall_x+", "wall_x-", "wall_y+", "wall_y-"))
    left, right = CELL.bins
    assert [p.name for p in CELL.places_for(left)][:2] == ["tray[0,0,0]", "tray[1,0,0]"]
    assert len(CELL.places_for(left)) == 6 and [p.name for p in CELL.places_for(right)] == ["chute"]
    assert right.rim_z < left.rim_z and CELL.picking_from("right").entry_z == pytest.approx(right.rim_z + 0.05)
    assert CELL.bin_of([0.5, -0.175, 0.03]) is right and CELL.bin_of([0.5, 0.0, 0.03]) is None
    assert CELL.next_bin("left") == "right" and CELL.next_bin("right") == "left"


def test_one_bin_spelling_is_a_list_of_one_named_bin() -> None:
    cell = resolve_cell("ur5e_bin_parallel")
    assert len(cell.bins) == 1 and cell.bin is cell.bins[0] and cell.bin.name == "bin"
    assert "bin/floor" in [b.name for b in cell.static_boxes]  # the one-bin box names are kept
    assert cell.places_for(cell.bin) == cell.places


_BIN = {"pose": {"xyz": [0.5, 0.0, 0.01]}, "inner_size": [0.3, 0.2, 0.1]}


@pytest.mark.parametrize(
    ("patch", "key", "words"),
    [
        (lambda d: d.update(bin=dict(_BIN)), "bins", "not both"),
        (lambda d: d.update(bins={"name": "a", **_BIN}), "bins", "a list of 1 to 16 bins"),
        (lambda d: d.update(bins=[]), "bins", "a list of 1 to 16 bins"),
        (lambda d: d["bins"][1].pop("name"), "bins[1].name", "every bin of a list has a name"),
        (lambda d: d["bins"][1].update(name="left"), "bins", "unique"),
        (lambda d: d["bins"][1].update(pose={"xyz": [0.5, 0.1, 0.01]}), "bins[1]", "overlaps bin 'left'"),
        (lambda d: d["bins"][0].update(plase=["tray"]), "bins[0].plase", "did you mean 'place'"),
        (lambda d: d["bins"][0].update(place=["tary"]), "bins[0].place[0]", "did you mean 'tray'"),
        (lambda d: d["bins"][0].update(place=[]), "bins[0].place", "non-empty list"),
        (lambda d: d["bins"][0].update(capture=0), "bins[0].capture", "needs a wrist camera"),
        (lambda d: d["bins"][0].update(capture=-1), "bins[0].capture", "index of a camera.capture pose"),
        (lambda d: d["bins"][1].update(inner_size=[0.3, 0.2]), "bins[1].inner_size", ""),
        (lambda d: d["bins"][1].update(wall_m=0.5), "bins[1].wall_m", ""),
    ],
)
def test_bad_bins_name_the_key(patch: Any, key: str, words: str) -> None:
    data = _data()
    patch(data)
    with pytest.raises(CellConfigError) as err:
        cell_from_dict(data)
    assert err.value.path == key and words in str(err.value), str(err.value)
    assert "\n" not in str(err.value)


def test_one_bin_spelling_is_validated_the_same_way() -> None:
    data = _data("ur5e_bin_parallel")
    data["bin"]["place"] = ["outfeed"]
    with pytest.raises(CellConfigError) as err:
        cell_from_dict(data)
    assert err.value.path == "bin.place[0]" and "no place named 'outfeed'" in str(err.value)
    data["bin"]["place"] = "outfeed_tray"
    assert cell_from_dict(data).bin.places == ("outfeed_tray",)  # type: ignore[union-attr]


def test_capture_index_of_a_wrist_camera_bin() -> None:
    data = _data("ur5e_wrist_camera")
    data["camera"]["flange_from_camera"] = {"xyz": [0.0, -0.07, 0.03], "rpy_deg": [0, 0, 0]}
    n = len(data["camera"]["capture"])
    data["bin"]["capture"] = n
    with pytest.raises(CellConfigError) as err:
        cell_from_dict(data)
    assert err.value.path == "bin.capture" and f"holds {n} pose(s)" in str(err.value)
    data["bin"]["capture"] = n - 1
    assert cell_from_dict(data).bin.capture == n - 1  # type: ignore[union-attr]


def test_a_part_in_bin_b_is_planned_with_bin_b_entry_exit_and_places() -> None:
    left, right = CELL.bins
    # the turn starts at bin 'left', which holds nothing: the part in 'right' is planned, with right's rim
    plan = plan_pick([_fit([0.5, -0.175, 0.025], 1)], [], CELL)
    assert plan.status == "ok" and plan.bin == "right" and plan.bins_empty == ("left",)
    assert plan.place == "chute"  # right's parts go to the chute, never to left's tray
    entry_b = CELL.picking_from("right").entry_z
    entry_a = CELL.entry_z
    assert entry_b < entry_a - 0.04
    assert _tcp_z(plan, "entry") == pytest.approx(max(entry_b, _tcp_z(plan, "pre_grasp")), abs=1e-6)
    assert _tcp_z(plan, "entry") < entry_a - 0.04 and _tcp_z(plan, "retreat") < entry_a
    doc = plan.to_json()
    assert doc["bin"] == "right" and doc["bins_empty"] == ["left"]
    check_plan(parse_plan(doc), SafetyLimits.from_cell(CELL))  # execution's judge accepts it

    # with a part in each bin, the cell's current bin goes first, and its part goes to its own place
    both = [_fit([0.5, 0.175, 0.025], 1), _fit([0.5, -0.175, 0.025], 2)]
    first = plan_pick(both, [], CELL)
    assert first.bin == "left" and first.place.startswith("tray[") and first.bins_empty == ()
    assert first.chosen is not None and first.targets[first.chosen.candidate.target].instance_id == 1
    assert _tcp_z(first, "entry") >= entry_a - 1e-6
    turn = plan_pick(both, [], CELL.picking_from("right"))
    assert turn.bin == "right" and turn.place == "chute"
    assert turn.chosen is not None and turn.targets[turn.chosen.candidate.target].instance_id == 2


def test_parts_in_no_bin_are_not_picked_and_every_bin_reads_empty() -> None:
    plan = plan_pick([_fit([0.5, 0.0, 0.025], 1)], [], CELL)  # on the table between the bins
    assert plan.status == "no_feasible_grasp" and plan.bins_empty == ("left", "right") and plan.bin == ""
    assert plan.to_json()["bins_empty"] == ["left", "right"]
    # a bin whose places are all filled is not picked from; the other bin still is
    no_tray = replace(CELL, places=tuple(p for p in CELL.places if p.name == "chute"))
    plan = plan_pick([_fit([0.5, 0.175, 0.025], 1), _fit([0.5, -0.175, 0.025], 2)], [], no_tray)
    assert plan.status == "ok" and plan.bin == "right"


class _NeverExhausted:
    """The synthetic bins, but never saying they are exhausted: the loop must stop on the planner's verdict."""

    def __init__(self, source: SyntheticBinSource) -> None:
        self.source = source

    exhausted = False

    def capture(self) -> Any:
        return self.source.capture()

    def check_pick(self, plan: PickPlan) -> str:
        return self.source.check_pick(plan)


@pytest.mark.parametrize("execute", [False, True])
def test_loop_empties_both_bins_in_turn_then_stops(execute: bool, caplog: pytest.LogCaptureFixture) -> None:
    """A dry run (sequential), and an execution on the simulated arm with overlapped cycles (the next turn is
    planned while the arm places: in the bin after this one)."""
    library = default_part_library()
    source = SyntheticBinSource(CELL, count=2, seed=3, validate_physics=False, library=library)
    held = sorted(CELL.bin_of(p[:3, 3]).name for p in source.layout.world_from_object)  # type: ignore[union-attr]
    assert held == ["left", "right"]
    driver = None
    if execute:
        driver = SimDriver(
            SafetyLimits.from_cell(CELL),
            q_home=np.asarray(CELL.home_q, dtype=np.float64),
            time_scale=10.0,
            options=DriverOptions(stale_state_s=1.0, watchdog_s=1.0),
        )
        driver.connect()
    try:
        with caplog.at_level(logging.INFO, logger="normpos_grasp.loop"):
            records = run_cell_loop(
                CELL, _NeverExhausted(source), source.ground_truth_segmenter(), library, driver, execute=execute,
                max_picks=5, overlap=execute,
            )  # fmt: skip
    finally:
        if driver is not None:
            driver.disconnect()
            driver.shutdown()
    docs = [r.plan_json or {} for r in records]
    assert [r.status for r in records] == ["picked" if execute else "dry_run"] * 2 + ["no_feasible_grasp"]
    assert [d.get("bin") for d in docs] == ["left", "right", ""]
    assert docs[0]["grasp"]["place"] == "tray[0,0,0]" and docs[1]["grasp"]["place"] == "chute"
    assert docs[1]["bins_empty"] == ["left"] and docs[2]["bins_empty"] == ["left", "right"]
    assert "bin 'left' empty" in caplog.text and "bin 'right' empty" in caplog.text
    assert "every bin of cell 'ur5e_two_bins' is empty" in caplog.text
    assert source.layout.n_parts == 0
    if execute:
        assert "overlap_wait" in records[1].timings_ms  # planned in the right bin while the arm placed the first part


def test_bins_region_covers_every_bin() -> None:
    region = CELL.bins_region(0.15)
    assert region is not None
    pose, size = region
    for b in CELL.bins:
        lx, ly, h = b.inner_size
        for dx in (-lx / 2, lx / 2):
            for dy in (-ly / 2, ly / 2):
                corner = b.world_from_bin @ np.array([dx, dy, h, 1.0])
                local = np.linalg.inv(pose) @ corner
                assert np.all(np.abs(local[:3]) <= size / 2 + 1e-9)
    one = resolve_cell("ur5e_bin_parallel")
    pose, size = one.bins_region(0.15)  # type: ignore[misc]
    assert np.allclose(size, [0.4, 0.3, 0.3]) and np.allclose(pose[:3, 3], [0.5, 0.0, 0.16])
    assert copy.deepcopy(size).shape == (3,)


def test_a_two_bin_turn_replays_from_the_bin_it_started_at(tmp_path: Path) -> None:
    """The second turn starts at bin 'right' (the bin after the one picked first): its bundle records that, and
    the replay plans from 'right' byte for byte as the loop did."""
    from normpos_grasp.pipeline import PipelineOptions
    from normpos_grasp.replay import BundleRecorder, assert_replays, load_bundle

    library = default_part_library()
    source = SyntheticBinSource(CELL, count=2, seed=3, validate_physics=False, library=library)
    segmenter = source.ground_truth_segmenter()
    with BundleRecorder(tmp_path / "bundles", segmenter) as recorder:
        records = run_cell_loop(
            CELL, source, segmenter, library, None, max_picks=2, options=PipelineOptions(fit_workers=1),
            bundles=recorder,
        )  # fmt: skip
    assert [(r.plan_json or {}).get("bin") for r in records] == ["left", "right"]
    second = load_bundle(recorder.saved[1])
    assert second.cell.bin is not None and second.cell.bin.name == "right"
    report = assert_replays(second)
    assert report.plan_json is not None and report.plan_json["bin"] == "right"
