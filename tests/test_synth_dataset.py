"""Synthetic frames and BOP export: GT instances, round trip through the BOP reader, byte-identical reruns, CLI."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2  # noqa: F401  (a hard dependency: imported, never skipped)
import mujoco  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import pytest
import trimesh  # noqa: F401  (a hard dependency: imported, never skipped)

import normpos_grasp.sim  # noqa: F401  (sets MUJOCO_GL=egl before mujoco loads)
from normpos_grasp.cli.main import main
from normpos_grasp.errors import InputError
from normpos_grasp.io.bop import read_models, read_split
from normpos_grasp.sim.cameras import CameraOptions
from normpos_grasp.sim.dataset import generate_frame, write_bop_dataset
from normpos_grasp.sim.parts import part_library_by_name
from normpos_grasp.sim.scene import SceneOptions


def test_generate_frame_ground_truth() -> None:
    sf = generate_frame(SceneOptions(count=6, seed=2), "d435", CameraOptions(resolution=(320, 240)), seed=4)
    assert sf.frame.rgb.shape == (240, 320, 3) and sf.frame.depth_m.shape == (240, 320)
    assert sf.camera.world_from_camera is not None
    assert len(sf.visib_fractions) == sf.layout.n_parts == 6
    assert sf.instances, "parts in the bin must be visible from above"
    for inst in sf.instances:
        k = inst.source_id
        assert inst.label == sf.layout.templates[k].label and inst.instance_id == k + 1
        assert np.array_equal(inst.mask, sf.rendering.instance_ids == k + 1)
        assert sf.visib_fractions[k] > 0
    # noisy depth stays near the ideal depth where both are valid (d435 at < 1 m: a few mm)
    both = (sf.frame.depth_m > 0) & (sf.rendering.depth_m > 0)
    assert np.median(np.abs(sf.frame.depth_m[both] - sf.rendering.depth_m[both])) < 0.005
    again = generate_frame(SceneOptions(count=6, seed=2), "d435", CameraOptions(resolution=(320, 240)), seed=4)
    assert np.array_equal(again.frame.depth_m, sf.frame.depth_m) and np.array_equal(again.frame.rgb, sf.frame.rgb)


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "ds"
    calls: list[tuple[int, int]] = []
    write_bop_dataset(
        out,
        2,
        2,
        sensor="d435",
        resolution=(320, 240),
        parts=["cube", "ring", "bracket"],
        seed=9,
        progress=lambda d, t: calls.append((d, t)),
        scene_options=SceneOptions(count=5),
    )
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]
    return out


def test_bop_round_trip(dataset: Path) -> None:
    models = read_models(dataset / "models")
    lib = part_library_by_name()
    assert sorted(models) == [1, 7, 8]  # the parts' own obj_ids (cube 1, bracket 7, ring 8), not their positions
    ring = models[8]
    assert ring.diameter_m == pytest.approx(lib["ring"].diameter_m, abs=1e-6)
    assert len(ring.symmetries_continuous) == 1 and len(models[1].symmetries_discrete) == 23
    scenes = read_split(dataset / "train")
    assert [s.scene_id for s in scenes] == [0, 1]
    for scene in scenes:
        assert scene.frame_ids == [0, 1]
        for im_id in scene.frame_ids:
            frame = scene.load_frame(im_id)
            cam = frame.camera
            assert cam.world_from_camera is not None and (cam.width, cam.height) == (320, 240)
            gts = scene.gt(im_id)
            info = scene.gt_info(im_id)
            assert len(gts) == len(info) == 5
            for idx, gt in enumerate(gts):
                assert gt.obj_id in (1, 7, 8)
                # world pose from the GT and the camera extrinsics: a part resting in the bin
                wfo = cam.world_from_camera @ gt.camera_from_object
                assert -0.01 < wfo[2, 3] < 0.2 and np.all(np.abs(wfo[:2, 3]) < 0.25)
                full, vis = scene.mask(im_id, idx), scene.mask_visib(im_id, idx)
                assert not np.any(vis & ~full)
                assert info[idx]["px_count_visib"] == int(vis.sum())
                if vis.any():
                    # rendered depth of the visible pixels agrees with the GT model surface (noise of a few mm)
                    d = frame.depth_m[vis]
                    assert np.median(d[d > 0]) == pytest.approx(gt.camera_from_object[2, 3], abs=0.05)
    static = (dataset / "train" / "000000" / "scene_static.json").read_text()
    assert "bin_wall_px" in static and (dataset / "parts.json").is_file() and (dataset / "camera.json").is_file()


def test_same_seed_gives_identical_bytes(dataset: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    write_bop_dataset(
        again,
        2,
        2,
        sensor="d435",
        resolution=(320, 240),
        parts=["cube", "ring", "bracket"],
        seed=9,
        scene_options=SceneOptions(count=5),
    )
    assert _tree_digest(again) == _tree_digest(dataset)


def test_cli_synth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli"
    code = main(
        [
            "synth",
            "--out",
            str(out),
            "--scenes",
            "1",
            "--frames",
            "1",
            "--sensor",
            "zivid",
            "--resolution",
            "240x160",
            "--parts",
            "sphere,plate",
            "--count",
            "3",
            "--seed",
            "1",
            "--no-progress",
        ]
    )
    assert code == 0
    assert "wrote 1 frames" in capsys.readouterr().out
    assert (out / "train" / "000000" / "depth" / "000000.png").is_file()
    assert main(["synth", "--out", str(out), "--resolution", "big"]) == 2
    with pytest.raises(InputError, match="unknown part"):
        write_bop_dataset(tmp_path / "x", 1, 1, parts=["gear"])
