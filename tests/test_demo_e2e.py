"""The demo end to end on a small bin (2 parts, at most 2 picks) through the loopback UR controller and the real
ur_rtde client; its report files parse; the HTML report and the live view render in headless Chromium."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import trimesh
from loopback import loopback_host
from test_report_viewer import _render_status

from normpos_grasp.cli.main import main

DEMO_HOST = loopback_host(93)  # one emulator per loopback address; the execution tests use others
PLAN_KEYS = {
    "format",
    "status",
    "robot",
    "world_from_base",
    "tool",
    "target",
    "grasp",
    "joint_waypoints",
    "trajectory",
    "candidates",
    "timing_ms",
}
SUMMARY_KEYS = {
    "picks_attempted",
    "picks_succeeded",
    "parts_left_in_bin",
    "stopped_because",
    "stop",
    "stop_parts",
    "pushes",
    "driver",
    "segmenter",
    "wall_time_s",
    "picks",
}


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("demo")
    argv = [
        "demo",
        "--out",
        str(out),
        "--parts",
        "2",
        "--max-picks",
        "2",
        "--seed",
        "3",
        "--segmenter",
        "gt",
        "--part-names",
        "cylinder,sphere,cube,box,bar",
        "--emulator-host",
        DEMO_HOST,
    ]
    import contextlib
    import io

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(argv)
    return {"code": code, "out": out, "stdout": stdout.getvalue()}


def test_demo_exits_0_through_the_emulator(demo: dict[str, Any]) -> None:
    assert demo["code"] == 0
    summary = json.loads((demo["out"] / "summary.json").read_text())
    assert set(summary) >= SUMMARY_KEYS
    assert summary["driver"] == "emulator", "the loopback UR controller did not start; see emulator.log"
    assert summary["picks_attempted"] >= 1
    assert 0 <= summary["picks_succeeded"] <= summary["picks_attempted"] <= 2
    assert 0 <= summary["parts_left_in_bin"] <= 2
    assert summary["parts_left_in_bin"] == 2 - summary["picks_succeeded"]
    # every stop says why, in one line (the same line the console prints)
    assert summary["stop"] and "\n" not in summary["stop"]
    assert f"stopped: {summary['stop']}" in demo["stdout"]
    if summary["parts_left_in_bin"] == 0:
        assert summary["stop"] == "the bin is empty"
    assert len(summary["picks"]) >= 1
    row = summary["picks"][0]
    for key in ("objects", "fits accepted", "target", "grasp", "joint path (rad)", "outcome"):
        assert key in row
    assert row["joint path (rad)"] > 0.0
    assert all(k in row for k in ("segment ms", "measure ms", "fit ms", "plan ms", "execute ms"))


def test_demo_report_files_parse(demo: dict[str, Any]) -> None:
    out: Path = demo["out"]
    overlay = cv2.imread(str(out / "overlay_01.png"))
    assert overlay is not None and overlay.ndim == 3 and overlay.shape[0] > 100
    glb = trimesh.load(out / "scene.glb")
    assert isinstance(glb, trimesh.Scene)
    names = set(glb.graph.nodes_geometry)
    for prefix in ("bin", "measured/", "fit/", "arm/", "tool/", "candidates/"):
        assert any(n.startswith(prefix) for n in names), f"no {prefix}* node in the GLB twin"
    assert any(n == "candidates/feasible" for n in names)
    plan = json.loads((out / "plan_01.json").read_text())
    assert set(plan) >= PLAN_KEYS
    assert plan["status"] == "ok"
    q = np.array([w["q"] for w in plan["joint_waypoints"]])
    assert q.shape[1] == 6 and len(q) >= 5
    timings = json.loads((out / "timings.json").read_text())
    assert timings[0]["pick"] == 1 and timings[0]["fit"] > 0.0
    page = (out / "report.html").read_text()
    assert "http://" not in page and "https://" not in page, "the report must not load anything from the network"


def test_demo_report_renders_in_chromium(demo: dict[str, Any], tmp_path: Path) -> None:
    status = _render_status((demo["out"] / "report.html").as_uri(), tmp_path)
    assert status["errors"] == "0", status["text"]
    assert int(status["nonempty"]) > 5000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_view_command_serves_the_demo_twin_live(demo: dict[str, Any], tmp_path: Path) -> None:
    port = _free_port()
    cmd = [
        sys.executable,
        "-m",
        "normpos_grasp.cli.main",
        "view",
        "--report",
        str(demo["out"]),
        "--port",
        str(port),
        "--seconds",
        "120",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        match = re.search(r"at (http://127\.0\.0\.1:\d+/)", line)
        assert match, f"view did not announce its URL: {line!r}"
        url = match.group(1)
        with urllib.request.urlopen(url + "scene.json", timeout=10) as resp:
            doc = json.loads(resp.read())
        assert doc["version"] == "1"
        names = {m["name"] for m in doc["scene"]["meshes"]}
        assert any(n.startswith("candidates/") for n in names)
        assert doc["state"]["file"] == "summary.json"
        with urllib.request.urlopen(url + "scene.json?since=1", timeout=10) as resp:
            assert json.loads(resp.read())["scene"] is None  # state-only polls stay small
        status = _render_status(url, tmp_path)
        assert status["errors"] == "0", status["text"]
        assert int(status["nonempty"]) > 5000
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


def test_live_view_follows_the_driver_state() -> None:
    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.cli.run import arm_state_dict
    from normpos_grasp.execution import SafetyLimits, SimDriver
    from normpos_grasp.report.live import LiveView

    cell = resolve_cell("ur5e_bin_parallel")
    driver = SimDriver(SafetyLimits.from_cell(cell), q_home=np.asarray(cell.home_q, dtype=np.float64))
    driver.connect()
    try:
        with LiveView(port=0) as view:
            view.follow(lambda: arm_state_dict(driver.state(), cell.world_from_base), period_s=0.05)
            deadline = time.monotonic() + 20
            state = None
            while time.monotonic() < deadline:
                with urllib.request.urlopen(view.url + "scene.json", timeout=10) as resp:
                    state = json.loads(resp.read())["state"]
                if state is not None:
                    break
                time.sleep(0.05)
    finally:
        driver.disconnect()
        driver.shutdown()
    assert state is not None, "the follower published no arm state"
    assert np.allclose(state["joints_rad"], cell.home_q, atol=1e-4)
    assert state["robot_mode"] == 7 and state["protective_stop"] is False
    assert len(state["tcp_xyz_m"]) == 3
