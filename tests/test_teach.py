"""`teach`: symmetry detection on meshes with known groups, a part taught with a tiny budget end to end, bad CAD
refused in one line with nothing written, and a taught part through synth -> estimate (ids kept), simulate and
demo with --library. The parts (tests/teach_parts.py) are built with trimesh here; none ships with the project."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from normpos_grasp.cli.main import main
from normpos_grasp.errors import MeshError
from normpos_grasp.teach import TeachOptions, check_cad, resting_poses, teach
from normpos_grasp.templates.library import load_library, resolve_library
from normpos_grasp.templates.symmetry import detect_symmetry

sys.path.insert(0, str(Path(__file__).parent))
import teach_parts

TINY = TeachOptions(budget_s=8.0, rest_samples=400, max_poses=2, grasps_per_pose=1, trials=2)


def _group_order(mesh: trimesh.Trimesh) -> tuple[int, int]:
    sym = detect_symmetry(mesh).symmetry
    return len(sym.discrete), len(sym.continuous)


@pytest.mark.parametrize(
    ("name", "make", "expected"),
    [
        ("box", lambda: trimesh.creation.box(extents=(0.06, 0.04, 0.03)), (3, 0)),  # D2: three half-turns
        ("hexagonal prism", lambda: trimesh.creation.cylinder(radius=0.02, height=0.012, sections=6), (11, 0)),  # D6
        ("cylinder", lambda: trimesh.creation.cylinder(radius=0.02, height=0.07, sections=64), (1, 1)),  # axis + flip
        ("sphere", lambda: trimesh.creation.icosphere(subdivisions=4, radius=0.02), (0, 3)),
        ("asymmetric", lambda: teach_parts.asymmetric_block().apply_scale(1e-3), (0, 0)),
    ],
)
def test_symmetry_of_known_groups(name: str, make: object, expected: tuple[int, int]) -> None:
    mesh = make()  # type: ignore[operator]
    assert _group_order(mesh) == expected, name


def test_detected_transforms_map_the_mesh_onto_itself() -> None:
    mesh = trimesh.creation.cylinder(radius=0.02, height=0.012, sections=6)
    mesh.apply_translation((0.003, -0.002, 0.001))  # off the origin: the axes pass through the centre of mass
    report = detect_symmetry(mesh)
    local = mesh.copy()
    local.apply_translation(-report.centre)
    v = np.asarray(local.vertices)
    assert len(report.symmetry.discrete) == 11
    for t in report.symmetry.discrete:
        assert np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-9) and np.linalg.det(t[:3, :3]) > 0
        moved = v @ t[:3, :3].T + t[:3, 3]
        _, dist, _ = trimesh.proximity.ProximityQuery(local).on_surface(moved)
        assert dist.max() < 1e-4


def test_resting_poses_of_a_plate_favour_its_broad_faces(tmp_path: Path) -> None:
    path = tmp_path / "plate80.stl"
    trimesh.creation.box(extents=(80.0, 50.0, 10.0)).export(str(path))
    t = check_cad(path)
    poses = resting_poses(t, samples=2000, seed=1)
    assert sum(p.probability for p in poses) == pytest.approx(1.0)
    # 80 x 50 x 10 mm, no symmetry given yet: six faces; lying flat (either broad face) is by far the likeliest
    assert len(poses) == 6 and {abs(round(p.down[2])) for p in poses[:2]} == {1} and poses[0].probability > 0.3
    assert poses[0].probability + poses[1].probability > 0.7


@pytest.fixture(scope="module")
def taught(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cad = tmp_path_factory.mktemp("cad")
    lib = tmp_path_factory.mktemp("lib") / "my_parts"
    path = teach_parts.write_part("t_profile", cad)
    parts = teach([path], lib, TINY)
    assert [p.template.name for p in parts] == ["t_profile"]
    return lib


def test_tiny_budget_teach_writes_a_ready_part(taught: Path) -> None:
    folder = taught / "t_profile"
    assert {p.name for p in folder.iterdir()} >= {"template.yaml", "mesh.stl", "report.html", ".prepared"}
    assert not [p for p in taught.iterdir() if p.name.startswith(".")]  # no staging left behind
    spec = yaml.safe_load((folder / "template.yaml").read_text())
    assert spec["obj_id"] == 101 and spec["units"] == "mm"
    assert spec["teach"]["symmetry"] == "2-fold about z"
    tried = {tr["grasp"] for tr in spec["teach"]["trials"]}
    assert tried  # the budget always leaves the first grasp its trials
    rates = {g["id"]: g["success_rate"] for g in spec["grasps"] if "success_rate" in g}
    assert all(0.5 <= r <= 1.0 for r in rates.values())  # tried and kept: at least half of the trials held
    assert tried == set(rates) | set(spec["teach"]["grasps_dropped"])  # each tried grasp: kept with its rate or dropped
    assert sum(p["probability"] for p in spec["teach"]["resting_poses"]) == pytest.approx(1.0, abs=1e-3)
    report = (folder / "report.html").read_text()
    assert report.count("data:image/png;base64,") >= 2 and "2-fold about z" in report
    t = load_library(taught).get("t_profile")
    assert t.obj_id == 101 and len(t.symmetry.discrete) == 1 and t.grasps


def test_taught_part_first_fit_pays_no_preparation(taught: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from collections import OrderedDict

    from normpos_grasp.templates import prepared

    def no_build(mesh: object) -> None:
        raise AssertionError("the preparation was rebuilt instead of loaded from the template folder")

    monkeypatch.setattr(prepared, "_BY_KEY", OrderedDict())  # as in a fresh process
    monkeypatch.setattr(prepared, "_compute", no_build)
    monkeypatch.setenv(prepared.CACHE_ENV, str(taught / "no-user-cache"))  # only the template's own .prepared
    t = load_library(taught).get("t_profile")
    assert len(prepared.prepare(t).samples) == prepared.N_SAMPLES


def test_a_part_taught_again_in_the_same_process_stores_its_preparation(taught: Path, tmp_path: Path) -> None:
    """The mesh's preparation is shared in memory by the first teach; the second library still gets its own copy."""
    (part,) = teach([teach_parts.write_part("t_profile", tmp_path)], tmp_path / "lib2", TINY)
    assert list((part.folder / ".prepared").glob("*.npz"))


@pytest.mark.parametrize("case", ["mm_as_m", "open", "empty", "ten_metres"])
def test_bad_cad_is_one_line_and_writes_nothing(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cad = tmp_path / "cad"
    cad.mkdir()
    units = "mm"
    if case == "mm_as_m":
        path = teach_parts.write_part("hex_nut", cad)  # 24 mm across, in mm
        units = "m"
    elif case == "open":
        can = trimesh.creation.cylinder(radius=20.0, height=40.0, sections=32)
        can.update_faces(np.asarray(can.face_normals)[:, 2] < 0.9)  # no lid: a 32-sided hole, too big to fill
        path = cad / "open.stl"
        can.export(str(path))
    elif case == "empty":
        path = cad / "empty.stl"
        path.write_bytes(b"")
    else:
        path = cad / "huge.stl"
        trimesh.creation.box(extents=(10000.0, 300.0, 200.0)).export(str(path))  # 10 m in mm
    out = tmp_path / "lib"
    code = main(["teach", str(path), "--out", str(out), "--units", units, "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("normpos-grasp teach: error:"), err
    assert not out.exists()


def test_a_good_part_after_bad_cad_in_one_call_is_not_written(tmp_path: Path) -> None:
    good = teach_parts.write_part("t_profile", tmp_path)
    bad = tmp_path / "empty.stl"
    bad.write_bytes(b"")
    out = tmp_path / "lib"
    out.mkdir()
    with pytest.raises(MeshError):
        teach([good, bad], out, TINY)
    assert list(out.iterdir()) == []


def test_taught_part_keeps_its_obj_id_from_synth_to_estimate(
    taught: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ds = tmp_path / "ds"
    code = main(["synth", "--out", str(ds), "--library", "builtin", "--library", str(taught), "--parts",
                 "t_profile,cube", "--scenes", "1", "--count", "4", "--resolution", "320x240", "--seed", "5",
                 "--no-progress"])  # fmt: skip
    assert code == 0
    gt_ids = {int(k) for k in __import__("json").loads((ds / "parts.json").read_text())["parts"]}
    assert gt_ids == {1, 101}  # the parts' own ids, not their positions in --parts
    out = tmp_path / "est.csv"
    code = main(["estimate", str(ds / "train"), "--library", str(taught), "--library", "builtin", "--segmenter",
                 "gt", "--out", str(out)])  # fmt: skip
    assert code == 0
    rows = list(csv.DictReader(out.open()))
    assert rows and {int(r["obj_id"]) for r in rows} <= gt_ids
    capsys.readouterr()
    # the taught part's library missing: no pose for obj 101, and estimate says which ids it lacks
    code = main(["estimate", str(ds / "train"), "--segmenter", "gt", "--out", str(tmp_path / "e2.csv")])
    err = capsys.readouterr().err
    assert code == 0 and "101" in err and "not in the part library" in err


def test_unknown_part_name_lists_the_library(taught: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["synth", "--out", str(tmp_path / "ds"), "--library", str(taught), "--parts", "t_profil"])
    err = capsys.readouterr().err
    assert code == 2 and "t_profil" in err and "t_profile (101)" in err
    assert not (tmp_path / "ds").exists()
    lib = resolve_library(["builtin", str(taught)])
    assert lib.by_obj_id(101).name == "t_profile" and lib.get("cube").obj_id == 1


def test_taught_part_in_simulate_and_demo(taught: Path, tmp_path: Path) -> None:
    out = tmp_path / "sim"
    code = main(["simulate", "--cell", "ur5e_bin_parallel", "--library", str(taught), "--parts", "t_profile",
                 "--count", "1", "--scenes", "1", "--segmenter", "gt", "--out", str(out)])  # fmt: skip
    assert code == 0
    summary = __import__("json").loads((out / "summary.json").read_text())
    assert summary["by_part"]["t_profile"]["attempted"] >= 1
    demo = tmp_path / "demo"
    code = main(["demo", "--out", str(demo), "--library", str(taught), "--part-names", "t_profile", "--parts", "1",
                 "--max-picks", "1", "--segmenter", "gt", "--no-emulator"])  # fmt: skip
    assert code in (0, 1)
    picks = __import__("json").loads((demo / "summary.json").read_text())
    # the taught part was perceived and fitted; it is then picked or the stop names it with the planner's reasons
    assert picks["picks"][0]["objects"] == 1 and picks["picks"][0]["fits accepted"] == "1/1"
    assert picks["picks"][0]["target"] == "t_profile" or "t_profile" in picks["stop"]
