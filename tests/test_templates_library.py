"""Template library: YAML folders, BOP models, save/load round trip, mesh checks and unit mix-ups."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.errors import MeshError, TemplateError
from normpos_grasp.templates.library import (
    TemplateLibrary,
    load_library,
    load_template,
    save_template,
)
from normpos_grasp.templates.mesh_check import check_mesh

REPO = Path(__file__).resolve().parents[1]


def _write(folder: Path, text: str, mesh: trimesh.Trimesh, name: str = "mesh.stl") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    mesh.export(str(folder / name))
    (folder / "template.yaml").write_text(text)
    return folder


def test_example_library_loads_with_units_symmetry_and_grasps() -> None:
    lib = load_library(REPO / "examples" / "templates")
    cube = lib.get("cube_40mm")
    assert cube.label == "cube"
    assert np.allclose(cube.extents_m, 0.04)
    assert len(cube.symmetry.discrete) == 23  # the full proper rotation group of a cube, from 2 generators
    assert np.allclose(cube.control_points["corner_ppp"], [0.02, 0.02, 0.02])
    assert cube.grasps[0].opening_m == pytest.approx(0.05)
    assert lib.by_label("bracket")[0].name == "l_bracket"
    v = np.asarray(cube.mesh.vertices)
    for s in cube.symmetry.discrete:  # every declared symmetry maps the mesh onto itself
        moved = v @ s[:3, :3].T + s[:3, 3]
        assert np.min(np.linalg.norm(moved[:, None] - v[None], axis=-1), axis=1).max() < 1e-9


def test_save_and_load_round_trip(tmp_path: Path) -> None:
    lib = load_library(REPO / "examples" / "templates")
    for t in lib:
        save_template(t, tmp_path / t.name, units="mm")
    back = load_library(tmp_path)
    assert back.names == lib.names
    for a in lib:
        b = back.get(a.name)
        assert np.allclose(a.extents_m, b.extents_m)
        assert a.symmetry.discrete and len(a.symmetry.discrete) == len(b.symmetry.discrete)
        for name, p in a.control_points.items():
            assert np.allclose(p, b.control_points[name])
        for ga, gb in zip(a.grasps, b.grasps, strict=True):
            assert np.allclose(ga.object_from_tcp, gb.object_from_tcp, atol=1e-9)
            assert ga.opening_m == pytest.approx(gb.opening_m)


def test_units_in_metres_and_mismatch_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    box_m = trimesh.creation.box(extents=(0.05, 0.03, 0.02))
    t = load_template(_write(tmp_path / "m", "name: b\nunits: m\n", box_m))
    assert np.allclose(sorted(t.extents_m), [0.02, 0.03, 0.05])
    # a mesh in metres declared as mm: 50 um across -> warned, then refused as implausibly small
    with caplog.at_level(logging.WARNING), pytest.raises(MeshError, match="units"):
        load_template(_write(tmp_path / "mm", "name: b\nunits: mm\n", box_m))
    assert any("metres" in r.message for r in caplog.records)
    # a mesh in mm declared as m: 50 m across
    with pytest.raises(MeshError, match="units"):
        load_template(_write(tmp_path / "big", "name: b\nunits: m\n", trimesh.creation.box(extents=(50, 30, 20))))


def test_bad_inputs_raise_typed_errors(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(TemplateError, match="no templates"):
        load_library(tmp_path / "empty")
    with pytest.raises(TemplateError, match="does not exist"):
        load_library(tmp_path / "nope")
    box = trimesh.creation.box(extents=(0.05, 0.03, 0.02))
    with pytest.raises(TemplateError, match="units"):
        load_template(_write(tmp_path / "u", "name: b\nunits: inch\n", box))
    with pytest.raises(TemplateError, match="not found"):
        load_template(_write(tmp_path / "nomesh", "name: b\nmesh: missing.stl\n", box))
    with pytest.raises(TemplateError, match="YAML|mapping"):
        load_template(_write(tmp_path / "bad", "- just\n- a list\n", box))
    # yaml.safe_load only: a python object tag is refused
    with pytest.raises(TemplateError):
        load_template(_write(tmp_path / "evil", "!!python/object/apply:os.system ['true']\n", box))
    with pytest.raises(TemplateError, match="unique"):
        t = load_template(_write(tmp_path / "ok", "name: b\nunits: m\n", box))
        TemplateLibrary((t, t))


def test_mesh_repair_reports_and_fixes(caplog: pytest.LogCaptureFixture) -> None:
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    inverted = trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False)
    faces = np.vstack([inverted.faces, inverted.faces[:2], [[0, 0, 1]]])  # duplicates + a degenerate face
    broken = trimesh.Trimesh(inverted.vertices, faces, process=False)
    with caplog.at_level(logging.WARNING):
        fixed, report = check_mesh(broken, "broken")
    assert report.ok and report.watertight and report.flipped
    assert report.duplicate_faces >= 2 and report.degenerate_faces >= 1
    assert fixed.volume > 0 and len(fixed.faces) == 12
    assert len(broken.faces) == 15  # input untouched
    assert "repaired" in caplog.text
    # an open surface is reported (and refused when a watertight mesh is required)
    open_mesh = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    _, rep = check_mesh(open_mesh, "open", repair=False)
    assert not rep.watertight and rep.problems
    with pytest.raises(MeshError, match="watertight"):
        check_mesh(open_mesh, "open", repair=False, require_watertight=True)
    with pytest.raises(MeshError):
        check_mesh(trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False), "flat")


def test_bop_models_folder_loads_as_library(lmo_sample: Path) -> None:
    lib = load_library(lmo_sample / "models")
    t = lib.by_obj_id(5)
    assert t.name == "obj_000005" and t.units == "mm"
    assert t.diameter_m == pytest.approx(0.20140, abs=2e-4)  # models_info.json: 201.40 mm
    assert np.allclose(t.extents_m, [0.10079, 0.18180, 0.19373], atol=2e-4)


def _one_template(root: Path, name: str, obj_id: int | None = None) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    trimesh.creation.box(extents=(30.0, 20.0, 10.0)).export(str(folder / "mesh.stl"))
    spec = f"name: {name}\nunits: mm\nshape: box\n" + (f"obj_id: {obj_id}\n" if obj_id is not None else "")
    (folder / "template.yaml").write_text(spec)
    return folder


def test_resolve_library_mixes_builtin_and_user_parts_with_stable_ids(tmp_path: Path) -> None:
    from normpos_grasp.templates.library import resolve_library

    _one_template(tmp_path / "lib", "spacer")  # no obj_id: the next above every declared one
    _one_template(tmp_path / "lib", "washer", 40)
    assert [t.obj_id for t in resolve_library()] == [1, 2, 3, 4, 5, 6, 7, 8]  # the default: the built-in parts
    mixed = resolve_library(["builtin", str(tmp_path / "lib")])
    assert mixed.get("washer").obj_id == 40 and mixed.get("spacer").obj_id == 41 and mixed.get("ring").obj_id == 8
    assert resolve_library([str(tmp_path / "lib"), "builtin"]).get("spacer").obj_id == 41  # order does not matter
    with pytest.raises(TemplateError, match=r"unknown part names \['nut'\].*spacer \(41\)"):
        mixed.subset(["nut"])


def test_resolve_library_refuses_clashing_names_and_ids(tmp_path: Path) -> None:
    from normpos_grasp.templates.library import resolve_library

    _one_template(tmp_path / "a", "cube")
    with pytest.raises(TemplateError, match="part name 'cube' is in both builtin and"):
        resolve_library(["builtin", str(tmp_path / "a")])
    _one_template(tmp_path / "b", "spacer", 3)
    with pytest.raises(TemplateError, match="obj_id 3 is used by 'bar'"):
        resolve_library(["builtin", str(tmp_path / "b")])


_BOX_YAML = "name: slab\nunits: mm\nshape: box\nmesh: mesh.stl\n"


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        ("grasp: []\n", "grasp: unknown key; did you mean 'grasps'"),
        ("label: [a]\n", "label: expected non-empty text"),
        ("obj_id: two\n", "obj_id: expected a whole number"),
        ("obj_id: 0\n", "obj_id: expected a whole number"),
        ("mass_kg: heavy\n", "mass_kg: expected a finite number"),
        ("control_points: [1, 2, 3]\n", "control_points: expected a mapping"),
        ("control_points: {far: [2000, 0, 0]}\n", "control_points.far: .* outside the part's bounding box"),
        ("grasps: [{id: g, scheme: parallel, position: [0, 0, 500]}]\n", "grasp 'g': its TCP .* outside"),
        ("grasps: [{id: g, scheme: parallel, opening: -5}]\n", r"grasps\[0\].opening: expected a length >= 0"),
        ("grasps: [{id: g, scheme: parallel, priority: .nan}]\n", r"grasps\[0\].priority: expected a finite"),
        ("grasps: [{id: g, scheme: parallel, matrix: [1, 2]}]\n", r"grasps\[0\].matrix: expected 4x4"),
        ("grasps: [{id: g, scheme: parallel, matrix: [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]\n", "not a rigid"),
        ("grasps: [{id: g, scheme: parallel}, {id: g, scheme: suction}]\n", "ids must be unique"),
        ("grasps: [{id: g, scheme: parallel, widht: 3}]\n", "widht: unknown key"),
        ("symmetry: {discrete: [{axis: [0, 0, 1], angle_deg: 90}]}\n", "does not map the mesh onto itself"),
        ("symmetry: {continuous: [{axis: [0, 0, 1]}]}\n", r"continuous\[0\] .* does not map the mesh onto itself"),
        ("symmetry: {discrete: {axis: [0, 0, 1]}}\n", "symmetry.discrete: expected a list of mappings"),
        ("symmetry: {discret: []}\n", "symmetry.discret: unknown key; did you mean 'discrete'"),
    ],
)
def test_a_bad_template_field_is_one_clear_error(tmp_path: Path, extra: str, match: str) -> None:
    """A 60 x 30 x 10 mm slab: every field a careless file gets wrong is refused naming the field (before, a typo
    was ignored, a 90 degree 'symmetry' of a 2:1 box was believed, a grasp 0.5 m off the part was kept)."""
    folder = _write(tmp_path / "slab", _BOX_YAML + extra, trimesh.creation.box((60.0, 30.0, 10.0)))
    with pytest.raises(TemplateError, match=match):
        load_template(folder)


def test_true_and_nearly_true_symmetries_are_kept(tmp_path: Path) -> None:
    """The slab's half turns pass; so does a continuous axis of a pin with a 1 mm deep flat along its side (a CAD
    detail the declaration ignores), but not of one with a 6 mm flat."""
    slab = _write(
        tmp_path / "slab",
        _BOX_YAML + "symmetry: {discrete: [{axis: [0, 0, 1], angle_deg: 180}, {axis: [1, 0, 0], angle_deg: 180}]}\n",
        trimesh.creation.box((60.0, 30.0, 10.0)),
    )
    assert len(load_template(slab).symmetry.discrete) == 2
    pin = "name: pin\nunits: mm\nshape: cylinder\nmesh: mesh.stl\nsymmetry: {continuous: [{axis: [0, 0, 1]}]}\n"
    for depth_mm, kept in ((1.0, True), (6.0, False)):
        flat = trimesh.creation.cylinder(radius=20.0, height=30.0, sections=96)
        v = np.array(flat.vertices)
        v[:, 0] = np.minimum(v[:, 0], 20.0 - depth_mm)
        flat.vertices = v
        folder = _write(tmp_path / f"pin_{depth_mm:g}", pin, flat)
        if kept:
            assert len(load_template(folder).symmetry.continuous) == 1
        else:
            with pytest.raises(TemplateError, match="does not map the mesh onto itself"):
                load_template(folder)
