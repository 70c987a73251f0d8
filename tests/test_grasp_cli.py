"""`normpos-grasp plan`: argument handling and clear failures (exit code 2 with one line)."""

from __future__ import annotations

from pathlib import Path

import pytest

from normpos_grasp.cli.main import build_parser, main

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"


def test_plan_command_is_registered() -> None:
    args = build_parser().parse_args(["plan", "scene", "--cell", "c.yaml", "--im-id", "3", "--out", "p.json"])
    assert args.command == "plan" and args.im_id == 3 and args.segmenter == "gt"


def test_bad_cell_file_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cell = tmp_path / "cell.yaml"
    cell.write_text("robot: {model: ur99}\n", encoding="utf-8")
    rc = main(["plan", str(tmp_path), "--cell", str(cell), "--im-id", "0", "--out", str(tmp_path / "p.json")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "robot.model" in err and "ur99" in err


def test_not_a_scene_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(
        [
            "plan",
            str(tmp_path),
            "--cell",
            str(EXAMPLES / "ur5e_bin_parallel.yaml"),
            "--im-id",
            "0",
            "--out",
            str(tmp_path / "p.json"),
        ]
    )
    assert rc == 2
    assert "not a BOP scene" in capsys.readouterr().err


def test_camera_without_extrinsics_exits_2(
    lmo_sample: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cell = (EXAMPLES / "ur10e_conveyor_suction.yaml").read_text(encoding="utf-8")
    cell = cell.replace("place:", f"templates: {lmo_sample / 'models'}\nplace:")
    path = tmp_path / "cell.yaml"
    path.write_text(cell, encoding="utf-8")
    rc = main(
        [
            "plan",
            str(lmo_sample / "test" / "000002"),
            "--cell",
            str(path),
            "--im-id",
            "3",
            "--out",
            str(tmp_path / "p.json"),
        ]
    )
    assert rc == 2
    assert "world_from_camera" in capsys.readouterr().err
