"""`normpos-grasp estimate` on a small synthetic BOP split: BOP results CSV with poses near the GT."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh  # noqa: F401  (a hard dependency: imported, never skipped)


def test_estimate_writes_bop_results(tmp_path: Path) -> None:
    from normpos_grasp.cli.main import main
    from normpos_grasp.sim.dataset import write_bop_dataset
    from normpos_grasp.sim.scene import SceneOptions

    split = write_bop_dataset(
        tmp_path / "ds", 1, 1, parts=["cube", "bracket"], scene_options=SceneOptions(count=3), split="test", seed=3
    )
    out = tmp_path / "results.csv"
    rc = main(
        ["estimate", str(split), "--models", str(tmp_path / "ds" / "models"), "--out", str(out), "--segmenter", "gt"]
    )
    assert rc == 0
    rows = list(csv.DictReader(out.open()))
    assert rows and list(rows[0]) == ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
    gt = json.loads((split / "000000" / "scene_gt.json").read_text())["0"]
    for r in rows:
        rot = np.array(r["R"].split(), dtype=float).reshape(3, 3)
        t = np.array(r["t"].split(), dtype=float)
        assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-6)
        same = [np.array(g["cam_t_m2c"]) for g in gt if g["obj_id"] == int(r["obj_id"])]  # parts may repeat
        assert min(np.linalg.norm(t - g) for g in same) < 5.0  # mm
        assert 0.0 < float(r["score"]) <= 1.0 and float(r["time"]) > 0


def test_estimate_bad_split_is_a_clean_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from normpos_grasp.cli.main import main

    (tmp_path / "models").mkdir()
    rc = main(["estimate", str(tmp_path / "nope"), "--models", str(tmp_path / "models"), "--out", "x.csv"])
    assert rc == 2
    assert "error" in capsys.readouterr().err
