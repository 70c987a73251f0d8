"""Failure tracing in simulate: every failed pick and part left has a stage, a detail and a picture; the cause table
lists them (console and failures.html) and the pictures are written with the scene."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import trimesh

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.geometry import make_pose
from normpos_grasp.records.template import Template
from normpos_grasp.sim.cameras import camera_intrinsics
from normpos_grasp.simulate.batch import BatchResult, RunFolder, scene_from_json, scene_to_json, write_results
from normpos_grasp.simulate.episode import PickRecord, SceneResult, SimulationConfig
from normpos_grasp.simulate.trace import (
    LeftPart,
    cause_rows,
    dominant_reason,
    failure_picture,
    format_cause_table,
)

CELL = Path(__file__).resolve().parents[1] / "examples" / "cells" / "ur5e_bin_parallel.yaml"
PIC = "failures/scene_000000_pick_01.png"


def _pick(pick: int, success: bool, cause: str = "", detail: str = "", picture: str = "") -> PickRecord:
    nan = float("nan")
    return PickRecord(
        0, pick, success, cause, "cube" if success else "", "", "", "", "", nan, nan, nan, nan, nan, 2, 1, 1, 0, 0, 0,
        1.0, 0.0, detail, picture,
    )  # fmt: skip


def _png() -> bytes:
    ok, buf = cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))
    assert ok
    return bytes(buf.tobytes())


def _scene() -> SceneResult:
    picks = (_pick(0, True), _pick(1, False, "no_feasible_grasp", "collision_cell", PIC))
    left = (LeftPart("plate", "no_feasible_grasp", "collision_cell"), LeftPart("ring", "mask", "not segmented"))
    return SceneResult(0, 3, False, picks, 2, left, ((PIC, _png()),))


def test_cause_table_lists_each_failure_with_its_picture() -> None:
    rows = cause_rows([_scene()])
    assert rows[0] == {
        "stage": "no_feasible_grasp",
        "detail": "collision_cell",
        "failed_picks": 1,
        "parts_left": 1,
        "picture": PIC,
    }
    assert rows[1]["stage"] == "mask" and rows[1]["parts_left"] == 1 and rows[1]["picture"] == PIC
    text = format_cause_table(rows)
    assert "collision_cell" in text and PIC in text and "not segmented" in text
    assert "none" in format_cause_table([])
    assert dominant_reason({"not_evaluated": 50, "stroke": 3, "collision_cell": 7}) == "collision_cell"
    assert dominant_reason({}) == "no_candidates"


def test_pictures_are_written_with_the_scene_and_linked_from_the_report(tmp_path: Path) -> None:
    folder = RunFolder(tmp_path)
    folder.start({"x": 1})
    scene = _scene()
    folder.write_scene(scene)
    assert (tmp_path / PIC).read_bytes() == _png()
    loaded = scene_from_json(json.loads(folder.scene_path(0).read_text()))
    assert loaded.left == scene.left  # pictures are files, not scene data

    def key(s: SceneResult) -> list[tuple[str, str, str]]:
        return [(p.cause, p.detail, p.picture) for p in s.picks]

    assert key(loaded) == key(scene)
    assert "pictures" not in json.dumps(scene_to_json(scene))
    summary = write_results(BatchResult(SimulationConfig(cell_path=str(CELL)), (loaded,)), tmp_path)
    assert summary["causes"][0]["picture"] == PIC
    page = (tmp_path / "failures.html").read_text()
    assert f'src="{PIC}"' in page and "collision_cell" in page
    header = (tmp_path / "picks.csv").read_text().splitlines()[0].split(",")
    assert header[header.index("detail") :][:2] == ["detail", "picture"]  # the grasp's origin columns follow
    folder.clear()
    assert not (tmp_path / "failures").exists()


def test_failure_picture_draws_the_true_part_and_the_caption() -> None:
    camera = camera_intrinsics("d435", (320, 240)).with_extrinsics(
        make_pose(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.6])  # looking straight down from 60 cm
    )
    frame = RGBDFrame(np.full((240, 320, 3), 90, np.uint8), np.full((240, 320), 0.6), camera)
    cube = Template("cube", "cube", trimesh.creation.box((0.05, 0.05, 0.05)), shape="box")
    png = failure_picture(frame, [], [], [(cube, make_pose(None, [0.0, 0.0, 0.025]))], [], "physics: drop")
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (240, 320, 3)
    white = np.all(img == 255, axis=2)
    assert white[:30].any()  # the caption
    assert white[100:140, 140:180].any()  # the true part's outline around the image centre
    assert not white[200:, :40].any()
