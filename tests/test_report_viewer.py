"""The report's files: GLB loads back in trimesh; the HTML page renders non-empty WebGL pixels in headless Chromium."""

from __future__ import annotations

import re
import shutil
import subprocess
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.camera import Camera
from normpos_grasp.geometry import make_pose
from normpos_grasp.records.instance import Instance
from normpos_grasp.report.gltf import GLTF_FROM_WORLD
from normpos_grasp.report.html import report_page, write_page
from normpos_grasp.report.live import LiveView
from normpos_grasp.report.overlay import OutlineItem, draw_overlay, encode_png
from normpos_grasp.report.scene3d import TwinScene

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROME_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--virtual-time-budget=4000",
    "--dump-dom",
]


def _scene() -> TwinScene:
    scene = TwinScene()
    scene.add_box("table", np.eye(4), np.array([0.8, 0.6, 0.02]), (180, 180, 180))
    pose = np.eye(4)
    pose[2, 3] = 0.05
    scene.add_posed_mesh("part", trimesh.creation.cylinder(radius=0.03, height=0.08), pose, (200, 60, 60), 0.7)
    rng = np.random.default_rng(0)
    scene.add_points("measured", rng.normal(scale=0.02, size=(300, 3)) + [0, 0, 0.1], (30, 30, 220))
    scene.add_capsule("link", pose, 0.02, 0.1, (60, 60, 60))
    scene.add_axes("tcp", pose)
    return scene


def _render_status(url: str, tmp_path: Path) -> dict[str, str]:
    if CHROMIUM is None:
        pytest.skip("headless Chromium is not installed (apt-get install chromium); .ci/run installs it")
    out = subprocess.run(
        [CHROMIUM, *CHROME_FLAGS, f"--user-data-dir={tmp_path / 'chrome'}", url],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    match = re.search(r'<div id="status"([^>]*)>(.*?)</div>', out.stdout)
    assert match, f"no status element in the page; chromium said: {out.stderr[-800:]}"
    attrs = dict(re.findall(r'data-(\w+)="([^"]*)"', match.group(1)))
    attrs["text"] = match.group(2)
    return attrs


def test_glb_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "scene.glb"
    _scene().export_glb(path)
    loaded = trimesh.load(path)
    assert isinstance(loaded, trimesh.Scene)
    assert len(loaded.geometry) >= 5
    world = _scene().bounds()
    corners = trimesh.transform_points(trimesh.bounds.corners(world), GLTF_FROM_WORLD)  # glTF is y-up
    assert np.allclose(loaded.bounds, [corners.min(0), corners.max(0)], atol=1e-6)
    assert np.allclose(TwinScene.from_glb(path).bounds(), world, atol=1e-6)  # `view` reads it back z-up


def test_report_page_renders_in_chromium(tmp_path: Path) -> None:
    camera = Camera(np.array([[500.0, 0, 160], [0, 500.0, 120], [0, 0, 1]]), 320, 240)
    mask = np.zeros((240, 320), dtype=bool)
    mask[100:140, 140:200] = True
    box = trimesh.creation.box(extents=[0.05, 0.05, 0.05])
    verts = np.asarray(box.vertices) + [0, 0, 0.5]
    picture = draw_overlay(
        np.full((240, 320, 3), 90, dtype=np.uint8),
        camera,
        [Instance(mask, "cube", 0.9)],
        [OutlineItem(verts, np.asarray(box.faces), "cube fit", (0, 255, 0))],
        grasp_world_from_tcp=make_pose(translation=[0.0, 0.0, 0.45]),
        grasp_opening_m=0.05,
    )
    assert picture.shape == (240, 320, 3)
    assert np.any(picture[mask] != 90), "mask not drawn"
    assert np.any(picture[~mask] != 90), "outline/grasp not drawn outside the mask"
    page = tmp_path / "report.html"
    write_page(page, report_page("test report", _scene(), {"overlay": encode_png(picture)}, {"Summary": "<p>ok</p>"}))
    status = _render_status(page.as_uri(), tmp_path)
    assert status["errors"] == "0", status["text"]
    assert int(status["nonempty"]) > 5000
    assert int(status["frames"]) >= 1


def test_live_view_serves_and_renders(tmp_path: Path) -> None:
    with LiveView(port=0) as view:
        view.publish(_scene(), {"joints": [0.0] * 6, "mode": "idle"})
        with urllib.request.urlopen(view.url + "scene.json", timeout=10) as resp:
            assert b'"mode": "idle"' in resp.read()
        status = _render_status(view.url, tmp_path)
    assert status["errors"] == "0", status["text"]
    assert int(status["nonempty"]) > 5000


def test_live_view_binds_loopback_only() -> None:
    with LiveView(port=0) as view:
        assert view.url.startswith("http://127.0.0.1:")
