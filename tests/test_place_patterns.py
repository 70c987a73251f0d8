"""Place patterns (issue 19 item 6): grid / stacked slots from the cell YAML, the part's orientation at the place
from its fitted pose, slots used once and the parts left there in the collision world of later plans."""

from __future__ import annotations

import copy
from importlib import resources
from typing import Any

import numpy as np
import pytest
import yaml

from normpos_grasp.cell.config import cell_from_dict
from normpos_grasp.errors import CellConfigError


def _cell(place: list[dict[str, Any]]) -> dict[str, Any]:
    with resources.as_file(resources.files("normpos_grasp.examples").joinpath("cells", "ur5e_bin_parallel.yaml")) as p:
        data: dict[str, Any] = yaml.safe_load(p.read_text())
    data.pop("templates", None)
    data["place"] = place
    return data


TRAY = {"xyz": [0.0, -0.45, 0.0], "rpy_deg": [180, 0, 0]}


def test_pattern_expands_to_slots_in_filling_order() -> None:
    pattern = {"columns": 3, "rows": 2, "pitch_m": [0.1, 0.08], "layers": 2, "layer_height_m": 0.05}
    cell = cell_from_dict(_cell([{"name": "tray", "world_from_tcp": TRAY, "pattern": pattern, "align_part": True}]))
    assert len(cell.places) == 12
    assert [p.name for p in cell.places[:4]] == ["tray[0,0,0]", "tray[1,0,0]", "tray[2,0,0]", "tray[0,1,0]"]
    first, last = cell.places[0], cell.places[-1]
    assert last.name == "tray[2,1,1]" and all(p.single_use and p.align_part for p in cell.places)
    # columns along the pose's x (world +x), rows along its y (world -y: the TCP is turned over), layers up world z
    assert np.allclose(last.world_from_tcp[:3, 3] - first.world_from_tcp[:3, 3], [0.2, -0.08, 0.05])
    assert np.allclose(last.world_from_tcp[:3, :3], first.world_from_tcp[:3, :3])
    plain = cell_from_dict(_cell([{"name": "drop", "world_from_tcp": TRAY}])).places
    assert len(plain) == 1 and not plain[0].single_use and not plain[0].align_part


@pytest.mark.parametrize(
    ("place", "key", "words"),
    [
        ({"pattern": {"columns": 0}}, "place[0].pattern.columns", "1-100"),
        ({"pattern": {"colums": 2}}, "place[0].pattern.colums", "unknown key"),
        ({"pattern": {"columns": 2}}, "place[0].pattern.pitch_m", "at least 1 mm"),
        ({"pattern": {"layers": 3}}, "place[0].pattern.layer_height_m", "at least 1 mm"),
        ({"pattern": {"columns": 2, "pitch_m": [0.1]}}, "place[0].pattern.pitch_m", "[DX, DY]"),
        ({"pattern": {"columns": 30, "pitch_m": [0.1, 0.0]}}, "place[0].pattern", "outside motion.workspace"),
        ({"align_part": "yes"}, "place[0].align_part", "true or false"),
    ],
)
def test_bad_patterns_name_the_key(place: dict[str, Any], key: str, words: str) -> None:
    data = _cell([{"name": "tray", "world_from_tcp": TRAY, **copy.deepcopy(place)}])
    with pytest.raises(CellConfigError) as err:
        cell_from_dict(data)
    assert err.value.path == key and words in str(err.value)


def test_slots_fill_in_order_parts_aligned_and_left_in_the_world() -> None:
    from normpos_grasp.loop import SyntheticBinSource, run_cell_loop, with_placed
    from normpos_grasp.sim.parts import default_part_library

    pattern = {"columns": 2, "rows": 1, "pitch_m": [0.12, 0.0], "layers": 2, "layer_height_m": 0.06}
    tray = {"name": "tray", "world_from_tcp": TRAY, "pattern": pattern, "align_part": True, "approach_m": 0.12}
    cell = cell_from_dict(_cell([tray]))
    library = [t for t in default_part_library() if t.name in ("box", "bar", "cube")]
    source = SyntheticBinSource(cell, 4, seed=1, library=library, validate_physics=False)
    records = run_cell_loop(cell, source, source.ground_truth_segmenter(), library, None, max_picks=3)
    done = [r for r in records if r.status == "dry_run"]
    assert len(done) == 3, [(r.status, r.plan_json and r.plan_json["candidates"]) for r in records]
    used = [r.plan_json["grasp"]["place"] for r in done if r.plan_json is not None]
    assert used == ["tray[0,0,0]", "tray[1,0,0]", "tray[0,0,1]"]  # each slot once, in order, then the next layer
    for record in done:
        plan = record.result.plan
        assert plan is not None and plan.chosen is not None
        c = plan.chosen.candidate
        release = next(w for w in plan.waypoints if w.name == "place")
        world_from_object = (
            release.world_from_tcp @ np.linalg.inv(c.world_from_tcp) @ plan.targets[c.target].world_from_object
        )
        x = world_from_object[:3, 0]
        if np.hypot(x[0], x[1]) > 1e-3:  # the part's x axis lies along the slot's x axis (world +x) ...
            yaw = float(np.degrees(np.arctan2(x[1], x[0])))
            if abs(yaw) > 0.05:  # ... or the release is the aligned one turned half a turn about the vertical
                # through the part's centre, taken only where the part lands on the same vertices (a box-like bar)
                assert abs(yaw) == pytest.approx(180.0, abs=0.05)
                verts = np.asarray(plan.targets[c.target].mesh.vertices, dtype=np.float64)
                placed = verts @ world_from_object[:3, :3].T + world_from_object[:3, 3]
                centre = 0.5 * (placed.min(axis=0) + placed.max(axis=0))
                aligned = (placed - centre) * [-1.0, -1.0, 1.0] + centre
                gaps = np.linalg.norm(placed[:, None, :] - aligned[None, :, :], axis=2).min(axis=1)
                assert gaps.max() < 1e-4, gaps
    # the part left in the first slot is a static box of the cell the next plan is made in
    after = with_placed(cell, done[0].result.plan)  # type: ignore[arg-type]
    assert [p.name for p in after.places] == ["tray[1,0,0]", "tray[0,0,1]", "tray[1,0,1]"]
    box = after.static_boxes[-1]
    assert box.name == "placed/tray[0,0,0]"
    assert abs(box.world_from_box[0, 3] - cell.places[0].world_from_tcp[0, 3]) < 0.05
    assert len(after.static_boxes) == len(cell.static_boxes) + 1
