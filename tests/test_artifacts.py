"""Files other tools read: the twin's GLB (glTF 2.0 rules, y-up, shading normals), arm links drawn where FK puts
them, BOP model PLYs readable under the BOP toolkit's rules (triangles only), and the LICENSE."""

from __future__ import annotations

import json
import struct
import tomllib
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

from normpos_grasp.cell.config import load_cell
from normpos_grasp.io.bop import load_mesh, read_models, write_models
from normpos_grasp.io.ply import read_ply, triangulate_faces, write_mesh_ply
from normpos_grasp.report.gltf import GLTF_FROM_WORLD, crease_normals, linear_to_srgb, srgb_to_linear
from normpos_grasp.report.scene3d import TwinScene, capsule_mesh

ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------------
# glTF: a reader of the container written from the spec's rules (chunks, bufferViews, accessors)
# --------------------------------------------------------------------------------------------------
_COMPONENT = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _read_glb(raw: bytes) -> tuple[dict[str, Any], bytes]:
    magic, version, length = struct.unpack_from("<III", raw, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(raw))
    json_len, json_type = struct.unpack_from("<II", raw, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0, "JSON chunk type / 4-byte padding"
    doc = json.loads(raw[20 : 20 + json_len])
    at = 20 + json_len
    if at == len(raw):
        return doc, b""
    bin_len, bin_type = struct.unpack_from("<II", raw, at)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0 and at + 8 + bin_len == len(raw), "BIN chunk"
    assert doc["buffers"][0]["byteLength"] <= bin_len and "uri" not in doc["buffers"][0]
    return doc, raw[at + 8 : at + 8 + bin_len]


def _accessor(doc: dict[str, Any], binary: bytes, index: int, vertex_attribute: bool) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(_COMPONENT[acc["componentType"]])
    width = _WIDTH[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride", dtype.itemsize * width)
    assert start % dtype.itemsize == 0, "accessor offset must be a multiple of its component size"
    if vertex_attribute:
        assert start % 4 == 0 and stride % 4 == 0, "vertex attribute elements must be 4-byte aligned"
        assert 4 <= stride <= 252
    assert acc.get("byteOffset", 0) + stride * (acc["count"] - 1) + dtype.itemsize * width <= view["byteLength"]
    assert view.get("byteOffset", 0) + view["byteLength"] <= len(binary)
    rows = [np.frombuffer(binary, dtype, width, start + i * stride) for i in range(acc["count"])]
    data = np.array(rows).reshape(acc["count"], width)
    if "min" in acc:  # must equal the stored values exactly
        assert np.array_equal(np.asarray(acc["min"], dtype=dtype), data.min(axis=0))
        assert np.array_equal(np.asarray(acc["max"], dtype=dtype), data.max(axis=0))
    return data


def _quat_matrix(xyzw: list[float]) -> np.ndarray:
    x, y, z, w = xyzw
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _twin() -> TwinScene:
    scene = TwinScene()
    scene.add_box("table", np.eye(4), np.array([0.8, 0.6, 0.02]), (180, 180, 180))
    pose = np.eye(4)
    pose[:3, 3] = [0.1, -0.05, 0.06]
    scene.add_posed_mesh("part", trimesh.creation.cylinder(radius=0.03, height=0.08), pose, (200, 60, 60), 0.55)
    scene.add_capsule("arm/link", pose, 0.02, 0.1, (90, 95, 105))
    rng = np.random.default_rng(4)
    scene.add_points("measured/1", rng.normal(scale=0.02, size=(500, 3)) + [0.0, 0.0, 0.1], (30, 30, 220))
    scene.add_axes("tcp", pose)
    return scene


def test_glb_follows_the_gltf_rules(tmp_path: Path) -> None:
    scene = _twin()
    path = tmp_path / "scene.glb"
    scene.export_glb(path)
    doc, binary = _read_glb(path.read_bytes())
    assert doc["asset"]["version"] == "2.0"
    root = doc["nodes"][doc["scenes"][doc["scene"]]["nodes"][0]]
    assert np.isclose(np.linalg.norm(root["rotation"]), 1.0)
    assert np.allclose(_quat_matrix(root["rotation"]), GLTF_FROM_WORLD[:3, :3], atol=1e-12)
    assert np.allclose(_quat_matrix(root["rotation"]) @ [0, 0, 1], [0, 1, 0])  # the world's up is glTF's +Y
    children = [doc["nodes"][i] for i in root["children"]]
    assert sorted(n["name"] for n in children) == sorted([m[0] for m in scene.meshes] + [c[0] for c in scene.clouds])
    by_name = {m[0]: m for m in scene.meshes}
    for node in children:
        prim = doc["meshes"][node["mesh"]]["primitives"][0]
        attrs = prim["attributes"]
        positions = _accessor(doc, binary, attrs["POSITION"], vertex_attribute=True)
        position_accessor = doc["accessors"][attrs["POSITION"]]
        assert position_accessor["componentType"] == 5126 and "min" in position_accessor and "max" in position_accessor
        material = doc["materials"][prim["material"]]
        if node["name"] in by_name:
            assert prim.get("mode", 4) == 4
            normals = _accessor(doc, binary, attrs["NORMAL"], vertex_attribute=True)
            assert normals.dtype == np.float32 and normals.shape == positions.shape
            assert np.allclose(np.linalg.norm(normals.astype(np.float64), axis=1), 1.0, atol=1e-6)
            idx = _accessor(doc, binary, prim["indices"], vertex_attribute=False).reshape(-1)
            assert doc["bufferViews"][doc["accessors"][prim["indices"]]["bufferView"]].get("byteStride") is None
            assert len(idx) % 3 == 0 and idx.max() < len(positions) and idx.max() < np.iinfo(idx.dtype).max
            _, _, color, opacity = by_name[node["name"]]
            factor = material["pbrMetallicRoughness"]["baseColorFactor"]
            assert np.allclose(factor[:3], srgb_to_linear(np.asarray(color) / 255.0)) and factor[3] == opacity
            assert material.get("alphaMode", "OPAQUE") == ("BLEND" if opacity < 1 else "OPAQUE")
            # the mesh's own vertices, not a copy of another's: same extent as the scene mesh, metres
            assert np.allclose(positions.min(0), by_name[node["name"]][1].bounds[0], atol=1e-6)
        else:
            assert prim["mode"] == 0 and "NORMAL" not in attrs
            colors = _accessor(doc, binary, attrs["COLOR_0"], vertex_attribute=True)
            assert np.allclose(linear_to_srgb(colors.astype(np.float64)) * 255.0, [30, 30, 220], atol=1e-3)
            assert "KHR_materials_unlit" in material["extensions"]
            assert "KHR_materials_unlit" in doc["extensionsUsed"]


def test_glb_opens_y_up_with_normals_in_trimesh(tmp_path: Path) -> None:
    scene = _twin()
    path = tmp_path / "scene.glb"
    scene.export_glb(path)
    loaded = trimesh.load(path, force="scene")
    world = scene.bounds()
    # glTF (x, y, z) = world (x, z, -y): the height of the cell is on glTF's Y axis
    assert np.allclose(loaded.bounds[:, 1], world[:, 2], atol=1e-6)
    assert np.allclose(loaded.bounds[:, 0], world[:, 0], atol=1e-6)
    assert np.allclose(sorted(-loaded.bounds[:, 2]), world[:, 1], atol=1e-6)
    table = loaded.dump(concatenate=False)
    meshes = {m.metadata.get("name", ""): m for m in table if isinstance(m, trimesh.Trimesh)}
    top = next(m for name, m in meshes.items() if name.startswith("table"))
    normals = np.asarray(top.vertex_normals)  # as stored in the file (24 vertices: split at the edges)
    assert len(normals) == 24
    on_top = np.all(np.asarray(top.vertices)[np.asarray(top.faces), 1] > 0.009, axis=1)  # in the viewer's frame
    assert on_top.sum() == 2 and np.allclose(normals[np.asarray(top.faces)[on_top]], [0.0, 1.0, 0.0], atol=1e-6)
    assert all(len(m.vertex_normals) == len(m.vertices) for m in meshes.values())


def test_glb_reads_back_z_up(tmp_path: Path) -> None:
    scene = _twin()
    path = tmp_path / "scene.glb"
    scene.export_glb(path)
    back = TwinScene.from_glb(path)
    assert np.allclose(back.bounds(), scene.bounds(), atol=1e-6)
    originals = {name: (mesh, color, opacity) for name, mesh, color, opacity in scene.meshes}
    for name, mesh, color, opacity in back.meshes:
        mesh0, color0, opacity0 = originals[name]
        assert np.allclose(mesh.bounds, mesh0.bounds, atol=1e-6), name
        assert abs(mesh.volume - mesh0.volume) < 1e-9 * max(1.0, abs(mesh0.volume)) + 1e-12, name
        assert np.abs(np.subtract(color, color0)).max() <= 3, (name, color, color0)  # 8-bit linear rounding
        assert abs(opacity - opacity0) < 1 / 255 + 1e-9
    assert np.allclose(back.clouds[0][1], scene.clouds[0][1], atol=1e-6)


def test_glb_leaves_out_meshes_without_area(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    scene = TwinScene()
    scene.add_box("table", np.eye(4), np.array([0.8, 0.6, 0.02]), (180, 180, 180))
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)  # collinear corners
    scene.add_mesh("sliver", flat, (10, 10, 10))
    scene.export_glb(tmp_path / "scene.glb")
    doc, _ = _read_glb((tmp_path / "scene.glb").read_bytes())
    assert [n["name"] for n in doc["nodes"][1:]] == ["table"]
    assert "sliver" in caplog.text


def test_crease_normals_split_sharp_edges_only() -> None:
    box = trimesh.creation.box(extents=[0.1, 0.2, 0.3])
    verts, faces, normals = crease_normals(box.vertices, box.faces)
    assert len(verts) == 24 and len(faces) == 12  # four corners per side
    face_normals = trimesh.Trimesh(verts, faces, process=False).face_normals
    assert np.allclose(normals[faces], face_normals[:, None, :], atol=1e-12)
    cyl = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=32)
    verts, faces, normals = crease_normals(cyl.vertices, cyl.faces)
    side = np.abs(normals[:, 2]) < 0.5
    assert side.sum() == 64  # one ring at each rim, shared by the side faces
    radial = np.column_stack([verts[side, :2] / 0.03, np.zeros(side.sum())])
    assert np.allclose(normals[side], radial, atol=1e-9)
    assert np.allclose(np.abs(normals[~side, 2]), 1.0)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    verts, faces, normals = crease_normals(sphere.vertices, sphere.faces)
    assert len(verts) == len(sphere.vertices)  # nothing split on a smooth surface
    assert np.einsum("ij,ij->i", normals, verts / 0.05).min() > 0.9999
    # unmerged input (an STL's triangle soup) is merged first; zero-area faces are dropped
    soup = np.asarray(box.vertices)[np.asarray(box.faces).reshape(-1)]
    tris = np.arange(len(soup)).reshape(-1, 3)
    tris = np.vstack([tris, [[0, 0, 1]]])
    verts, faces, _ = crease_normals(soup, tris)
    assert len(verts) == 24 and len(faces) == 12


# --------------------------------------------------------------------------------------------------
# arm links
# --------------------------------------------------------------------------------------------------
def _capsule_ends(mesh: trimesh.Trimesh, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Hemisphere centres of a capsule mesh, measured: its two farthest-apart vertices (the poles) less a radius."""
    v = np.asarray(mesh.vertices)
    d = np.linalg.norm(v[:, None] - v[None], axis=2)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    axis = (v[i] - v[j]) / d[i, j]
    return v[i] - radius * axis, v[j] + radius * axis


def test_capsule_is_centred_on_its_frame() -> None:
    mesh = capsule_mesh(0.05, 0.4)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert np.allclose(mesh.bounds, [[-0.05, -0.05, -0.25], [0.05, 0.05, 0.25]], atol=1e-12)
    exact = np.pi * 0.05**2 * 0.4 + 4.0 / 3.0 * np.pi * 0.05**3
    assert 0.95 * exact < mesh.volume < exact  # inscribed polygonal approximation


@pytest.mark.parametrize("seed", [0, 1])
def test_arm_links_are_drawn_at_the_joints(seed: int) -> None:
    from normpos_grasp.camera import Camera
    from normpos_grasp.camera.model import RGBDFrame
    from normpos_grasp.kinematics.robot import Robot
    from normpos_grasp.report.frame import FrameResult, frame_twin

    cell = load_cell(ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml")
    robot = Robot.load(cell.robot_model)
    lo, hi = robot.joint_limits
    q = np.random.default_rng(seed).uniform(np.maximum(lo, -np.pi), np.minimum(hi, np.pi))
    camera = Camera(np.array([[300.0, 0, 16], [0, 300.0, 12], [0, 0, 1]]), 32, 24)
    frame = RGBDFrame(np.zeros((24, 32, 3), np.uint8), np.zeros((24, 32)), camera)
    twin = frame_twin(FrameResult(frame, [], [], [], None, {}), cell, arm_q=q)
    drawn = {name: mesh for name, mesh, _, _ in twin.meshes if name.startswith("arm/")}
    world_from_link = {k: cell.world_from_base @ p for k, p in robot.link_poses(q).items()}
    shapes = robot.collision_geometry
    geo = robot.params.link_geometry
    sh, fa = geo.shoulder_offset, geo.shoulder_offset - geo.elbow_offset

    def on(link: str, z: float) -> np.ndarray:  # a point on joint `link`'s axis, z metres along it
        return (world_from_link[link] @ [0.0, 0.0, z, 1.0])[:3]

    expected = {  # capsule index in the UR layout -> its two hemisphere centres, from FK frames
        1: (on("shoulder", geo.base_height), on("upper_arm", 0.0)),
        2: (on("upper_arm", 0.0), on("upper_arm", sh)),
        3: (on("upper_arm", sh), on("forearm", sh)),  # the upper arm: joint 2 axis to joint 3 axis
        4: (on("forearm", fa), on("forearm", sh)),
        5: (on("forearm", fa), on("wrist_1", fa)),  # the forearm: joint 3 axis to joint 4 axis
        6: (on("wrist_1", fa), on("wrist_2", 0.0)),
        7: (on("wrist_2", 0.0), on("wrist_3", 0.0)),
    }
    assert [i for i, s in enumerate(shapes) if s.kind == "capsule"] == sorted(expected)
    for i, (a, b) in expected.items():
        p, r = _capsule_ends(drawn[f"arm/{shapes[i].link}/{i}"], shapes[i].size[0])
        err = min(max(np.linalg.norm(p - a), np.linalg.norm(r - b)), max(np.linalg.norm(p - b), np.linalg.norm(r - a)))
        assert err < 1e-6, (i, shapes[i].link, err)


# --------------------------------------------------------------------------------------------------
# BOP models: an independent reader that enforces what the BOP toolkit's load_ply relies on
# --------------------------------------------------------------------------------------------------
_TOOLKIT_TYPES = {"float": "<f4", "double": "<f8", "int": "<i4", "uchar": "u1"}  # the only binary types it reads


def _read_ply_toolkit_rules(path: Path) -> dict[str, np.ndarray]:
    """Read a PLY mesh the way the BOP toolkit can: a vertex element then a face element whose only property is
    `list uchar int vertex_indices` with 3 corners per face, vertex properties of type float/double/int/uchar,
    binary little-endian or ASCII. Raises ValueError where that reader would fail or misread."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    if lines[0] != "ply":
        raise ValueError("no ply magic")
    fmt, elements = "", []
    for line in lines[1:-1]:
        words = line.split()
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            elements[-1][2].append(words[1:])
    if fmt not in ("binary_little_endian", "ascii"):
        raise ValueError(f"format {fmt}: the toolkit reads native (little-endian) binary or ascii")
    if [e[0] for e in elements] != ["vertex", "face"] and [e[0] for e in elements] != ["vertex"]:
        raise ValueError(f"elements {[e[0] for e in elements]}: vertices then faces, nothing else")
    _, n_vert, vprops = elements[0]
    if any(p[0] == "list" or p[0] not in _TOOLKIT_TYPES for p in vprops):
        raise ValueError(f"vertex property types {vprops}")
    names = [p[1] for p in vprops]
    n_face, fprops = (elements[1][1], elements[1][2]) if len(elements) > 1 else (0, [])
    if n_face and fprops != [["list", "uchar", "int", "vertex_indices"]]:
        raise ValueError(f"face properties {fprops}: only 'list uchar int vertex_indices' is read in step")
    body = raw[end:]
    if fmt == "ascii":
        rows = body.decode("ascii").split("\n")
        table = np.array([r.split() for r in rows[:n_vert]], dtype=np.float64)
        face_rows = [np.array(r.split(), dtype=np.int64) for r in rows[n_vert : n_vert + n_face]]
        if any(len(f) != 4 or f[0] != 3 for f in face_rows):
            raise ValueError("Only triangular faces are supported.")
        faces = np.array([f[1:] for f in face_rows]).reshape(-1, 3)
        cols = {n: table[:, i] for i, n in enumerate(names)}
    else:
        vdt = np.dtype([(n, _TOOLKIT_TYPES[p[0]]) for n, p in zip(names, vprops, strict=True)])
        verts = np.frombuffer(body, vdt, n_vert)
        fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
        rest = body[vdt.itemsize * n_vert :]
        if len(rest) != fdt.itemsize * n_face:  # a 4-corner face or a skipped property shifts everything
            raise ValueError(f"face data is {len(rest)} bytes, {fdt.itemsize * n_face} expected for triangles")
        fdata = np.frombuffer(rest, fdt, n_face)
        if np.any(fdata["n"] != 3):
            raise ValueError("Only triangular faces are supported.")
        faces = fdata["i"].astype(np.int64)
        cols = {n: verts[n].astype(np.float64) for n in names}
    out = {"pts": np.column_stack([cols["x"], cols["y"], cols["z"]]), "faces": faces}
    if {"nx", "ny", "nz"} <= set(names):
        out["normals"] = np.column_stack([cols["nx"], cols["ny"], cols["nz"]])
    if len(faces) and (faces.min() < 0 or faces.max() >= n_vert):
        raise ValueError("face index out of range")
    return out


def _stl_derived(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh as it comes back from a binary STL (with trimesh's per-face 'stl' attribute)."""
    return trimesh.load(BytesIO(mesh.export(file_type="stl")), file_type="stl", force="mesh")


def test_toolkit_rules_reader_rejects_what_the_toolkit_cannot_read(tmp_path: Path) -> None:
    stl = _stl_derived(trimesh.creation.cylinder(radius=0.03, height=0.08, sections=24))
    assert "stl" in stl.face_attributes  # what made trimesh's own PLY export unreadable for the toolkit
    (tmp_path / "trimesh.ply").write_bytes(stl.export(file_type="ply", encoding="binary"))
    with pytest.raises(ValueError, match="face properties"):
        _read_ply_toolkit_rules(tmp_path / "trimesh.ply")
    quads = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    quads += "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    quads += "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    (tmp_path / "quad.ply").write_text(quads)
    with pytest.raises(ValueError, match="triangular"):
        _read_ply_toolkit_rules(tmp_path / "quad.ply")


def test_bop_models_load_under_the_toolkit_rules(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=[0.04, 0.06, 0.1])
    box.visual.face_colors = [200, 30, 30, 255]  # face colours must not reach the PLY either
    stl = _stl_derived(trimesh.creation.cylinder(radius=0.03, height=0.08, sections=24))
    write_models(tmp_path, [(1, box, None, None), (2, stl, None, [((0, 0, 1.0), (0, 0, 0))])])
    models = read_models(tmp_path)
    for obj_id, mesh in ((1, box), (2, stl)):
        path = tmp_path / f"obj_{obj_id:06d}.ply"
        model = _read_ply_toolkit_rules(path)
        assert np.allclose(model["pts"], np.asarray(mesh.vertices) * 1000.0, atol=1e-4)  # mm, float32
        assert np.array_equal(model["faces"], np.asarray(mesh.faces))
        assert np.allclose(np.linalg.norm(model["normals"], axis=1), 1.0, atol=1e-6)
        by_trimesh = trimesh.load(path, force="mesh", process=False)
        assert by_trimesh.is_watertight and np.isclose(by_trimesh.volume, mesh.volume * 1e9, rtol=1e-5)
        assert np.allclose(read_ply(path).points, model["pts"])
        loaded = load_mesh(models[obj_id])
        assert np.allclose(loaded.bounds, mesh.bounds, atol=1e-7)


def test_real_bop_model_reads_and_survives_our_writer(tmp_path: Path) -> None:
    source = ROOT.parent / "shared" / "data" / "lmo_sample" / "models"
    if not (source / "obj_000005.ply").is_file():
        pytest.skip(f"LM-O sample not found at {source} (CI clones shared/ beside)")
    original = _read_ply_toolkit_rules(source / "obj_000005.ply")  # the reader accepts a real BOP model (ascii)
    assert original["faces"].shape == (45666, 3)
    mesh = load_mesh(read_models(source)[5])  # metres
    write_models(tmp_path, [(5, mesh, None, None)])
    again = _read_ply_toolkit_rules(tmp_path / "obj_000005.ply")
    assert np.allclose(again["pts"], original["pts"], atol=1e-3) and np.array_equal(again["faces"], original["faces"])


def test_polygon_faces_are_written_as_triangles(tmp_path: Path) -> None:
    cube = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64) * 20.0
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    write_mesh_ply(tmp_path / "cube.ply", cube, quads)
    model = _read_ply_toolkit_rules(tmp_path / "cube.ply")
    assert model["faces"].shape == (12, 3)
    cube_mesh = trimesh.load(tmp_path / "cube.ply", force="mesh", process=False)
    assert cube_mesh.is_watertight and np.isclose(cube_mesh.volume, 8000.0)
    # a pentagonal prism given as two pentagons and five quads (ragged)
    ang = np.linspace(0.0, 2.0 * np.pi, 5, endpoint=False)
    ring = np.column_stack([np.cos(ang), np.sin(ang)])
    verts = np.vstack([np.column_stack([ring, np.zeros(5)]), np.column_stack([ring, np.ones(5)])])
    polys = [[4, 3, 2, 1, 0], [5, 6, 7, 8, 9]] + [[i, (i + 1) % 5, (i + 1) % 5 + 5, i + 5] for i in range(5)]
    tris = triangulate_faces(polys)
    assert tris.shape == (2 * 3 + 5 * 2, 3)
    write_mesh_ply(tmp_path / "prism.ply", verts, polys)
    model = _read_ply_toolkit_rules(tmp_path / "prism.ply")
    prism = trimesh.Trimesh(model["pts"], model["faces"], process=False)
    area = 0.5 * 5 * np.sin(2.0 * np.pi / 5)
    assert prism.is_watertight and prism.is_winding_consistent and np.isclose(prism.volume, area, rtol=1e-6)


# --------------------------------------------------------------------------------------------------
# LICENSE
# --------------------------------------------------------------------------------------------------
def test_license_matches_pyproject() -> None:
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"]
    assert declared == "Apache-2.0"
    text = (ROOT / "LICENSE").read_text()
    assert text.split()[:4] == ["Apache", "License", "Version", "2.0,"]
    for clause in ("1. Definitions.", "9. Accepting Warranty or Additional Liability.", "END OF TERMS AND CONDITIONS"):
        assert clause in text
    assert "Copyright 2026 normpos-grasp developers" in text
