"""Interrupted `simulate` runs: finished scenes kept, `--resume` gives the files of an uninterrupted run, refused when
the parameters differ; SIGINT / SIGTERM / the parent's death end the worker processes.

The CLI runs as a subprocess (the installed entry point, real signals) on the smallest real configuration: one cube
per scene at 160x120 with the ideal segmenter (a scene takes a few seconds).
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from normpos_grasp.errors import InputError
from normpos_grasp.simulate.batch import (
    RunFolder,
    run_batch,
    run_parameters,
    scene_from_json,
    scene_to_json,
)
from normpos_grasp.simulate.episode import PickRecord, SceneResult, SimulationConfig

ROOT = Path(__file__).resolve().parents[1]
CELL = ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml"
#: options of every simulated run here (the seed is added per test)
TINY = ("--cell", str(CELL), "--count", "1", "--parts", "cube", "--resolution", "160x120", "--segmenter", "gt")
#: files of a finished run that must be byte-identical between an uninterrupted and a resumed run
SAME = ("manifest.json", "picks.csv", "summary.json", "success_by_part.png", "success_by_depth.png",
        "success_by_occlusion.png")  # fmt: skip
WAIT_S = 240.0


def _cli(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "normpos_grasp.cli.main", "simulate", *TINY, "--out", str(out), "--no-progress",
            *extra]  # fmt: skip


def _start(out: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(_cli(out, *extra), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _run(out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(_cli(out, *extra), cwd=ROOT, capture_output=True, text=True, timeout=WAIT_S, check=False)


def _wait_for(predicate: object, proc: subprocess.Popen[str], what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not predicate():  # type: ignore[operator]
        if proc.poll() is not None:
            raise AssertionError(f"the run ended (code {proc.returncode}) before {what}: {proc.communicate()[1]}")
        if time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"no {what} within {WAIT_S} s")
        time.sleep(0.05)


def _proc_stat(pid: int) -> tuple[str, int] | None:
    """(state, parent pid) of a live process from /proc, None when it is gone (a zombie counts as gone)."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    state, ppid = text[text.rindex(")") + 2 :].split()[:2]
    return None if state in ("Z", "X") else (state, int(ppid))


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            stat = _proc_stat(int(entry.name))
            if stat is not None and stat[1] == pid:
                out.append(int(entry.name))
    return out


def _workers(pid: int) -> list[int]:
    """Scene workers (spawned multiprocessing children) of process `pid`."""
    found = []
    for child in _children(pid):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes()
        except FileNotFoundError:
            continue
        if b"spawn_main" in cmd:
            found.append(child)
    return found


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and real signals")


@pytest.mark.slow
def test_sigint_then_resume_gives_the_uninterrupted_files(tmp_path: Path) -> None:
    """Two scenes in one worker: SIGINT once scene 0 is written, then --resume runs scene 1 in a fresh process
    (no state carried over from scene 0); the results equal those of one uninterrupted run."""
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    reference = _start(ref, "--scenes", "2", "--seed", "4")
    interrupted = _start(cut, "--scenes", "2", "--seed", "4")
    try:
        first = cut / "scenes" / "scene_000000.json"
        _wait_for(first.is_file, interrupted, "first scene file")
        assert (cut / "manifest.json").is_file() and not (cut / "summary.json").exists()
        interrupted.send_signal(signal.SIGINT)
        _, err = interrupted.communicate(timeout=WAIT_S)
        assert interrupted.returncode == 130, err
        line = _one_line(err)
        assert "interrupted by SIGINT" in line and "1 of 2 scenes" in line and "--resume" in line
        assert sorted(p.name for p in (cut / "scenes").iterdir()) == ["scene_000000.json"]
        assert not (cut / "summary.json").exists() and not (cut / "picks.csv").exists()
        resumed = _run(cut, "--scenes", "2", "--seed", "4", "--resume")
        assert resumed.returncode == 0, resumed.stderr
        assert "1 scenes resumed" in resumed.stdout
        reference.communicate(timeout=WAIT_S)
        assert reference.returncode == 0
    finally:
        for proc in (reference, interrupted):
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    for name in SAME:
        assert (cut / name).read_bytes() == (ref / name).read_bytes(), name
    summary = json.loads((cut / "summary.json").read_text())
    assert summary["scenes"] == 2 and summary["picks_attempted"] >= 2
    timing = json.loads((cut / "timing.json").read_text())
    assert timing["scenes_resumed"] == 1 and timing["scenes_run"] == 1
    again = _run(cut, "--scenes", "2", "--seed", "4", "--resume")  # a complete run: nothing to do
    assert again.returncode == 0 and "already complete" in again.stdout
    assert (cut / "summary.json").read_bytes() == (ref / "summary.json").read_bytes()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_no_worker_outlives_the_parent(tmp_path: Path, sig: signal.Signals) -> None:
    """--workers 2: SIGTERM ends both workers and exits 143 with one line; after SIGKILL of the parent (no handler
    runs) the workers die through the parent-death signal."""
    proc = _start(tmp_path / "out", "--scenes", "4", "--seed", "1", "--workers", "2")
    try:
        _wait_for(lambda: len(_workers(proc.pid)) == 2, proc, "two workers")
        workers = _workers(proc.pid)
        children = _children(proc.pid)  # workers and multiprocessing's resource tracker
        time.sleep(1.0)  # the workers are simulating
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    if sig == signal.SIGTERM:
        assert proc.returncode == 143, err
        line = _one_line(err)
        assert "interrupted by SIGTERM" in line and "--resume" in line
    else:
        assert proc.returncode == -signal.SIGKILL
    deadline = time.monotonic() + 10.0
    while any(_proc_stat(p) is not None for p in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [p for p in workers if _proc_stat(p) is not None]
    assert not alive, f"worker processes {alive} outlived the run"
    assert all(_proc_stat(p) is None for p in children)
    assert (tmp_path / "out" / "manifest.json").is_file() and not (tmp_path / "out" / "summary.json").exists()


def _main(out: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, str]:
    """The CLI in this process (for runs refused before any scene starts): exit code and the stderr line."""
    from normpos_grasp.cli.main import main

    code = main(["simulate", *TINY, "--out", str(out), "--no-progress", *extra])
    return code, _one_line(capsys.readouterr().err)


def test_resume_with_other_parameters_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The manifest's parameters against the command's: another seed (or scene count) is one line, exit 2, and the
    run folder is left as it was."""
    out = tmp_path / "run"
    config = SimulationConfig(
        cell_path=str(CELL), seed=4, parts=("cube",), parts_per_scene=1, segmenter="gt", resolution=(160, 120)
    )
    folder = RunFolder(out)
    folder.start(run_parameters(config, 2))
    before = (out / "manifest.json").read_bytes()
    for extra, named in ((("--seed", "5", "--scenes", "2"), "seed 4 -> 5"), (("--seed", "4", "--scenes", "3"),
                                                                             "scenes 2 -> 3")):  # fmt: skip
        code, line = _main(out, capsys, *extra, "--resume")
        assert code == 2 and line.startswith("normpos-grasp simulate: error: --resume"), line
        assert named in line
    assert (out / "manifest.json").read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "scenes"]
    assert not any((out / "scenes").iterdir())
    code, line = _main(out, capsys, "--seed", "4", "--scenes", "2")  # no --resume / --overwrite: refused
    assert code == 2 and "--overwrite" in line


def test_resume_refuses_a_folder_that_is_no_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "other"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code, line = _main(out, capsys, "--seed", "4", "--scenes", "2", "--resume")
    assert code == 2 and "no manifest.json" in line
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def _pick(scene: int, pick: int, fit_error: float) -> PickRecord:
    return PickRecord(scene, pick, False, "wrong_fit", "cube", "primitive_cube_1", "parallel", "missed", "why, \"so\"",
                      0.1 + 0.2, 1.0 / 3.0, fit_error, float("nan"), 2.0**-40, 1, 1, 1, 0, 0, 0, 123.456789012345,
                      0.0)  # fmt: skip


def test_scene_files_round_trip_exactly(tmp_path: Path) -> None:
    """Scene files are lossless (NaN, inf and every float bit), partial leftovers are removed, and a file holding
    another scene or another format is refused."""
    folder = RunFolder(tmp_path / "run")
    config = SimulationConfig(cell_path=str(CELL))
    folder.start(run_parameters(config, 3))
    scene = SceneResult(1, 2, False, (_pick(1, 0, float("inf")), _pick(1, 1, 0.0123456789012345678)), 1)
    folder.write_scene(scene)
    (folder.scenes_dir / ".scene_000002.json.x.partial").write_text("{")  # left by a SIGKILL mid-write
    loaded = folder.load_scenes(3)
    assert list(loaded) == [1]
    back = loaded[1]
    assert back.picks[0].fit_error_m == math.inf and math.isnan(back.picks[0].slip_m)
    assert json.dumps([p.__dict__ for p in back.picks]) == json.dumps([p.__dict__ for p in scene.picks])  # NaN-safe
    assert back.picks[0].depth_m == 0.1 + 0.2 and back.picks[0].lift_m == 2.0**-40
    assert (back.scene, back.n_parts, back.cleared, back.parts_left) == (1, 2, False, 1)
    assert not list(folder.scenes_dir.glob(".*.partial"))
    folder.scene_path(0).write_text(json.dumps(scene_to_json(scene)))  # scene 1 under scene 0's name
    with pytest.raises(InputError, match="holds scene 1, not 0"):
        folder.load_scenes(3)
    with pytest.raises(InputError, match="not a simulate scene file"):
        scene_from_json({"format": "x"}, "f.json")
    with pytest.raises(InputError, match="malformed"):
        scene_from_json({**scene_to_json(scene), "picks": [{"scene": 1}]}, "f.json")


def test_run_parameters_cover_what_changes_results(tmp_path: Path) -> None:
    """Every config field, the scene count and the cell file's content are parameters; the workers are not."""
    base = SimulationConfig(cell_path=str(CELL))
    params = run_parameters(base, 5)
    assert params["scenes"] == 5 and params["seed"] == 0 and params["physics"]["timestep_s"] > 0
    assert params["cell_path"] == str(CELL.resolve()) and len(params["cell_sha256"]) == 64
    assert "workers" not in params and "ray" not in params
    for changed in (
        SimulationConfig(cell_path=str(CELL), seed=1),
        SimulationConfig(cell_path=str(CELL), sensor="ideal"),
        SimulationConfig(cell_path=str(CELL), parts=("cube",)),
        SimulationConfig(cell_path=str(CELL), gripper="2f140"),
        SimulationConfig(cell_path=str(CELL), resolution=(320, 240)),
        SimulationConfig(cell_path=str(CELL), segmenter="depth"),
        SimulationConfig(cell_path=str(CELL), reuse_fits=False),
    ):
        assert run_parameters(changed, 5) != params
    copy = tmp_path / "cell.yaml"
    copy.write_bytes(CELL.read_bytes() + b"\n# edited\n")
    assert run_parameters(SimulationConfig(cell_path=str(copy)), 5)["cell_sha256"] != params["cell_sha256"]
    folder = RunFolder(tmp_path / "run")
    folder.start(params)
    folder.check_resume(run_parameters(base, 5))  # the same parameters pass
    with pytest.raises(InputError, match=r"scenes 5 -> 6"):
        folder.check_resume(run_parameters(base, 6))


def test_finished_scenes_are_not_run_again() -> None:
    """run_batch with every scene in `done` runs nothing and returns them in scene order."""
    config = SimulationConfig(cell_path=str(CELL))
    done = {1: SceneResult(1, 1, True, (_pick(1, 0, 0.001),), 0), 0: SceneResult(0, 1, False, (), 1)}
    seen: list[int] = []
    result = run_batch(config, 2, done=done, on_scene=lambda r: seen.append(r.scene))
    assert [s.scene for s in result.scenes] == [0, 1] and seen == []


# -- synth ---------------------------------------------------------------------------------------------------
SYNTH = ("--scenes", "3", "--count", "2", "--resolution", "160x120", "--no-progress")


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_synth_sigterm_then_resume_gives_the_uninterrupted_dataset(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """SIGTERM once scene 0 is staged: exit 143, one line, no dataset at --out, scene 0 kept; --resume with another
    seed is refused; --resume writes the remaining scenes and the dataset equals an uninterrupted one file by file."""
    from normpos_grasp.cli.main import main

    ref, out = tmp_path / "ref", tmp_path / "out"
    staging = tmp_path / ".out.partial"
    args = [sys.executable, "-m", "normpos_grasp.cli.main", "synth", "--out", str(out), *SYNTH]
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for((staging / "train" / "000000").is_dir, proc, "the first staged scene")
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 143, err
    line = _one_line(err)
    assert "interrupted by SIGTERM" in line and "of 3 scenes finished" in line and "--resume" in line
    assert not out.exists() and (staging / "train" / "000000" / "scene_static.json").is_file()
    kept = _tree(staging / "train" / "000000")
    assert main(["synth", "--out", str(ref), *SYNTH]) == 0
    capsys.readouterr()
    assert main(["synth", "--out", str(out), *SYNTH, "--resume", "--seed", "9"]) == 2
    refused = _one_line(capsys.readouterr().err)
    assert "--resume" in refused and "seed 0 -> 9" in refused
    assert _tree(staging / "train" / "000000") == kept and not out.exists()
    assert main(["synth", "--out", str(out), *SYNTH, "--resume"]) == 0
    assert not staging.exists()
    assert _tree(out) == _tree(ref)
    assert main(["synth", "--out", str(out), *SYNTH, "--resume"]) == 0  # complete: nothing to do
    assert "already complete" in capsys.readouterr().out
