"""`normpos-grasp run`: dry run on a small BOP folder written by normpos_grasp.sim (ground-truth masks), synthetic:2
with --execute against the loopback UR controller, and an unreachable bin giving a 'no_feasible_grasp' record."""

from __future__ import annotations

import copy
import json
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from loopback import loopback_host

from normpos_grasp.cell import load_cell
from normpos_grasp.cli.main import main

RUN_HOST = loopback_host(94)  # one emulator per loopback address; the execution tests use others
PACKAGED = resources.files("normpos_grasp.examples")


def _packaged_cell_dict() -> dict[str, Any]:
    with resources.as_file(PACKAGED.joinpath("cells", "ur5e_bin_parallel.yaml")) as path:
        data: dict[str, Any] = yaml.safe_load(path.read_text())
    with resources.as_file(PACKAGED.joinpath("templates")) as templates:
        data["templates"] = str(templates)
    return data


def _shifted(data: dict[str, Any], dx: float, dy: float = 0.0) -> dict[str, Any]:
    """The same cell with its world frame moved: every world position gets (dx, dy, 0) added."""
    out = copy.deepcopy(data)

    def move(pose: dict[str, Any]) -> None:
        pose["xyz"] = [pose["xyz"][0] + dx, pose["xyz"][1] + dy, pose["xyz"][2]]

    move(out["robot"]["world_from_base"])
    move(out["table"]["pose"])
    move(out["bin"]["pose"])
    for fixture in out.get("fixtures", []):
        move(fixture["pose"])
    for place in out.get("place", []):
        move(place["world_from_tcp"])
    if "world_from_camera" in out.get("camera", {}):
        move(out["camera"]["world_from_camera"])
    ws = out["motion"]["workspace"]
    ws["min"] = [ws["min"][0] + dx, ws["min"][1] + dy, ws["min"][2]]
    ws["max"] = [ws["max"][0] + dx, ws["max"][1] + dy, ws["max"][2]]
    return out


def _write_cell(data: dict[str, Any], path: Path) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def bop_folder(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A one-frame BOP split of two parts in a bin of the packaged cell's size, and that cell re-expressed in the
    dataset's world (bin floor centre on the table at the origin, camera poses from the dataset)."""
    from normpos_grasp.sim.cell_scene import scene_options_for_cell
    from normpos_grasp.sim.dataset import write_bop_dataset

    tmp = tmp_path_factory.mktemp("bop_run")
    data = _packaged_cell_dict()
    cell = load_cell(_write_cell(data, tmp / "packaged.yaml"))
    dataset_cell = _shifted(data, -0.5)  # the packaged bin floor sits at (0.5, 0, 0) on the table
    dataset_cell["camera"] = {"from_scene": True}
    options = scene_options_for_cell(cell, 2, seed=4)
    split = write_bop_dataset(tmp / "bop", 1, 1, parts=["cube", "box"], seed=4, scene_options=options)
    return {"split": split, "cell": _write_cell(dataset_cell, tmp / "dataset_cell.yaml"), "tmp": tmp}


def test_run_dry_on_a_bop_folder(bop_folder: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    out = bop_folder["tmp"] / "dry"
    argv = [
        "run",
        "--cell",
        str(bop_folder["cell"]),
        "--source",
        str(bop_folder["split"]),
        "--robot",
        "127.0.0.1",
        "--segmenter",
        "gt",
        "--max-picks",
        "3",
        "--out",
        str(out),
    ]
    code = main(argv)
    printed = capsys.readouterr().out
    assert code == 0, printed
    run = json.loads((out / "run.json").read_text())
    assert run["mode"] == "dry run" and run["source_kind"] == "bop"
    assert [p["status"] for p in run["picks"]] == ["dry_run"]  # one frame in the folder: one turn
    plan = json.loads((out / "plan_01.json").read_text())
    assert plan["status"] == "ok" and plan["target"]["template"] in ("cube", "box")
    assert (out / "scene.glb").is_file()
    assert "pick 1: dry_run" in printed


def test_unreachable_bin_gives_no_feasible_grasp_record(bop_folder: dict[str, Path]) -> None:
    from normpos_grasp.cell.config import cell_from_dict
    from normpos_grasp.loop import BopFrameSource, run_cell_loop
    from normpos_grasp.sim.parts import default_part_library

    data = yaml.safe_load(bop_folder["cell"].read_text())
    data["robot"]["world_from_base"]["xyz"] = [-3.0, 0.0, 0.0]  # the bin is 3 m away from the arm
    data["motion"]["workspace"] = {"min": [-3.9, -0.9, -0.05], "max": [-2.1, 0.9, 0.9]}
    data["place"][0]["world_from_tcp"]["xyz"] = [-3.0, -0.45, 0.0]
    data["fixtures"] = []
    cell = cell_from_dict(data, bop_folder["tmp"])
    source = BopFrameSource(bop_folder["split"])
    library = [t for t in default_part_library() if t.name in ("cube", "box")]
    records = run_cell_loop(cell, source, source.ground_truth_segmenter(source.part_names()), library, None)
    assert len(records) == 1
    record = records[0]
    assert record.status == "no_feasible_grasp"
    assert record.execution is None
    doc = record.plan_json
    assert doc is not None and doc["status"] == "no_feasible_grasp"
    reasons = doc["candidates"]["rejected_by_reason"]
    assert reasons and set(reasons) <= {"workspace", "ik", "approach_angle", "stroke", "joint_limits"}, reasons
    assert len(record.result.accepted_fits) >= 1  # the parts were seen and fitted; only the arm cannot reach


def test_run_synthetic_executes_on_the_emulator(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from normpos_grasp.sim.ur_emulator.process import EmulatorProcess

    out = tmp_path / "exec"
    with EmulatorProcess(RUN_HOST, "ur5e", log_path=tmp_path / "emulator.log", verbose=0):
        argv = [
            "run",
            "--cell",
            "ur5e_bin_parallel",
            "--source",
            "synthetic:2",
            "--parts",
            "cylinder,sphere,cube,box,bar",
            "--seed",
            "7",
            "--robot",
            RUN_HOST,
            "--execute",
            "--max-picks",
            "1",
            "--view",
            "--view-port",
            "0",
            "--out",
            str(out),
        ]
        code = main(argv)
    printed = capsys.readouterr().out
    run = json.loads((out / "run.json").read_text())
    assert run["mode"] == "execute"
    assert [p["status"] for p in run["picks"]] in (["picked"], ["pick_failed"]), printed
    assert code == (0 if run["picks"][0]["status"] == "picked" else 1)
    assert "live view: http://127.0.0.1:" in printed
    plan = json.loads((out / "plan_01.json").read_text())
    assert plan["status"] == "ok"
    timings = run["picks"][0]["timings_ms"]
    assert timings["execute"] > 0.0 and np.isfinite(timings["check"])


def test_realsense_source_without_the_extra_says_how_to_install(capsys: pytest.CaptureFixture[str]) -> None:
    import importlib.util

    if importlib.util.find_spec("pyrealsense2") is not None:
        pytest.skip("pyrealsense2 is installed: the missing-extra message cannot be shown")
    code = main(["run", "--cell", "ur5e_bin_parallel", "--source", "realsense", "--robot", "127.0.0.1"])
    err = capsys.readouterr().err
    assert code == 2
    assert "pyrealsense2" in err and "normpos-grasp[camera]" in err


def test_run_rejects_an_unknown_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "--cell", "ur5e_bin_parallel", "--source", str(tmp_path / "nope"), "--robot", "127.0.0.1"])
    assert code == 2
    assert "neither a folder" in capsys.readouterr().err


def test_realsense_intrinsics_become_a_camera() -> None:
    from types import SimpleNamespace

    from normpos_grasp.realsense_source import camera_from_intrinsics

    intr = SimpleNamespace(
        fx=615.0,
        fy=614.0,
        ppx=321.5,
        ppy=242.0,
        width=640,
        height=480,
        model="distortion.brown_conrady",
        coeffs=[0.1, -0.2, 0.001, 0.002, 0.05],
    )
    pose = np.eye(4)
    pose[:3, 3] = [0.5, 0.0, 0.9]
    camera = camera_from_intrinsics(intr, 0.001, pose)
    assert camera.K[0, 0] == 615.0 and camera.K[1, 2] == 242.0 and (camera.width, camera.height) == (640, 480)
    assert np.allclose(camera.distortion, intr.coeffs) and np.allclose(camera.world_from_camera, pose)
    inverse = SimpleNamespace(**{**vars(intr), "model": "distortion.inverse_brown_conrady"})
    assert np.all(camera_from_intrinsics(inverse, 0.001, None).distortion == 0.0)  # not OpenCV's forward model
