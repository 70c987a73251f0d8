"""Binary glTF 2.0 (GLB) writer for coloured triangle meshes and point clouds, and shading normals.

glTF is y-up (spec section 3.4). Callers give geometry in a z-up world frame (metres); the document's single root
node carries the rotation `GLTF_FROM_WORLD`, so every viewer that follows the spec (three.js, Blender, the Khronos
sample viewer) shows the world's z axis pointing up while node-local positions stay in world coordinates.

Colours are given as 8-bit sRGB and written linear, as the spec wants for `baseColorFactor` and `COLOR_0`.
Meshes get per-vertex normals split at creases (`crease_normals`), so flat faces shade flat and curved ones smooth.
"""

from __future__ import annotations

import json
import logging
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from normpos_grasp.errors import InputError
from normpos_grasp.typing import FloatArray, IntArray

# (x, y, z)_world -> (x, z, -y)_glTF: a -90 degree turn about x takes the world's z-up to glTF's y-up.
GLTF_FROM_WORLD: FloatArray = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
GLTF_FROM_WORLD.setflags(write=False)
WORLD_FROM_GLTF: FloatArray = np.ascontiguousarray(GLTF_FROM_WORLD.T)
WORLD_FROM_GLTF.setflags(write=False)
_ROOT_ROTATION_XYZW = [-float(np.sqrt(0.5)), 0.0, 0.0, float(np.sqrt(0.5))]  # GLTF_FROM_WORLD as a quaternion

_FLOAT, _UINT16, _UINT32 = 5126, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TRIANGLES, _POINTS = 4, 0
_GLB_MAGIC, _CHUNK_JSON, _CHUNK_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class GltfMesh:
    """A triangle mesh in the world frame: vertices (N, 3) metres, faces (M, 3) indices, sRGB colour, opacity."""

    name: str
    vertices: FloatArray
    faces: IntArray
    color: tuple[int, int, int]
    opacity: float = 1.0


@dataclass(frozen=True, eq=False)
class GltfPoints:
    """A point cloud in the world frame: points (N, 3) metres, colours (N, 3) sRGB 0..255."""

    name: str
    points: FloatArray
    colors: FloatArray


def srgb_to_linear(srgb: FloatArray) -> FloatArray:
    """sRGB values in 0..1 to linear light (IEC 61966-2-1 transfer curve)."""
    c = np.clip(np.asarray(srgb, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: FloatArray) -> FloatArray:
    """Linear light in 0..1 to sRGB values in 0..1 (inverse of `srgb_to_linear`)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1.0 / 2.4) - 0.055)


def crease_normals(
    vertices: FloatArray, faces: IntArray, crease_deg: float = 35.0
) -> tuple[FloatArray, IntArray, FloatArray]:
    """Per-vertex unit normals for shading, with vertices split where neighbouring faces meet at more than
    `crease_deg` degrees (a box keeps sharp edges, a cylinder's side shades smooth).

    Vertices at the same position are merged first; zero-area faces are dropped. Returns (vertices (K, 3),
    faces (M', 3), normals (K, 3)); each normal is the corner-angle-weighted mean of the face normals it smooths
    over (angle weights keep a cylinder's side normals radial however its quads were split).
    """
    verts_in = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces_in = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces_in) and (faces_in.min() < 0 or faces_in.max() >= len(verts_in)):
        raise InputError(f"face indices must lie in 0..{len(verts_in) - 1}")
    verts, inverse = np.unique(verts_in, axis=0, return_inverse=True)
    tri = inverse.reshape(-1)[faces_in]
    weighted = np.cross(verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]])
    double_area = np.linalg.norm(weighted, axis=1)
    scale = float(np.ptp(verts, axis=0).max()) if len(verts) else 0.0
    keep = (double_area > (scale * 1e-9) ** 2) & (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2])
    keep &= tri[:, 2] != tri[:, 0]
    tri, weighted, double_area = tri[keep], weighted[keep], double_area[keep]
    n_faces = len(tri)
    if n_faces == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3))
    unit = weighted / double_area[:, None]
    # one row per directed face edge (a -> b) with the two corners (3 * face + k) it joins
    face_of = np.repeat(np.arange(n_faces), 3)
    k = np.tile(np.arange(3), n_faces)
    a, b = tri.reshape(-1), tri[:, [1, 2, 0]].reshape(-1)
    corner_a, corner_b = 3 * face_of + k, 3 * face_of + (k + 1) % 3
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((hi, lo))
    same = (lo[order][1:] == lo[order][:-1]) & (hi[order][1:] == hi[order][:-1])
    e1, e2 = order[:-1][same], order[1:][same]  # consecutive rows of one undirected edge
    smooth = np.einsum("ij,ij->i", unit[face_of[e1]], unit[face_of[e2]]) >= np.cos(np.radians(crease_deg))
    e1, e2 = e1[smooth], e2[smooth]
    aligned = a[e1] == a[e2]  # both faces list the edge in the same direction (inconsistent winding)
    join_u = np.concatenate([corner_a[e1], corner_b[e1]])
    join_v = np.concatenate(
        [np.where(aligned, corner_a[e2], corner_b[e2]), np.where(aligned, corner_b[e2], corner_a[e2])]
    )
    n_corners = 3 * n_faces
    graph = coo_matrix((np.ones(len(join_u)), (join_u, join_v)), shape=(n_corners, n_corners))
    n_out, label = connected_components(graph, directed=False)
    corner_xyz = verts[tri]  # (F, 3 corners, 3)
    to_next = np.roll(corner_xyz, -1, axis=1) - corner_xyz
    to_prev = np.roll(corner_xyz, 1, axis=1) - corner_xyz
    angle = np.arctan2(np.linalg.norm(np.cross(to_next, to_prev), axis=2), np.einsum("fki,fki->fk", to_next, to_prev))
    sums = np.zeros((n_out, 3))
    np.add.at(sums, label, angle.reshape(-1, 1) * unit[face_of])
    lengths = np.linalg.norm(sums, axis=1)
    fallback = np.zeros((n_out, 3))
    fallback[label] = unit[face_of]  # a face normal of the group, for sums that cancel
    cancelled = lengths <= 1e-9
    normals = np.where(cancelled[:, None], fallback, sums / np.where(cancelled, 1.0, lengths)[:, None])
    positions = np.zeros((n_out, 3))
    positions[label] = verts[tri.reshape(-1)]
    return positions, label.reshape(-1, 3).astype(np.int64), normals


class _Buffer:
    """The GLB's binary chunk: bufferViews aligned to 4 bytes, one accessor each (tightly packed)."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict[str, int]] = []
        self.accessors: list[dict[str, object]] = []

    def add(self, array: np.ndarray, component: int, kind: str, target: int, bounds: bool = False) -> int:
        raw = np.ascontiguousarray(array).tobytes()
        self.views.append({"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw), "target": target})
        self.data += raw + b"\0" * (-len(raw) % 4)
        accessor: dict[str, object] = {
            "bufferView": len(self.views) - 1,
            "componentType": component,
            "count": int(len(array)),
            "type": kind,
        }
        if bounds:
            flat = array.reshape(len(array), -1)
            accessor["min"] = [_number(x) for x in flat.min(axis=0)]
            accessor["max"] = [_number(x) for x in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _number(x: np.generic) -> float | int:
    """A JSON number that reads back to exactly the stored float32 / integer value."""
    return int(x) if np.issubdtype(type(x), np.integer) else float(x)


def glb_bytes(meshes: Sequence[GltfMesh], clouds: Sequence[GltfPoints], generator: str = "normpos-grasp") -> bytes:
    """One GLB document: a root node turning z-up into y-up, one child node per mesh / point cloud (same name).

    Meshes are TRIANGLES with POSITION, NORMAL and indices and a double-sided PBR material (alphaMode BLEND when
    opacity < 1; a mesh with no face of non-zero area is left out, with a warning); point clouds are POINTS with
    POSITION and COLOR_0 and an unlit material (KHR_materials_unlit).
    """
    buf = _Buffer()
    gltf_meshes: list[dict[str, object]] = []
    materials: list[dict[str, object]] = []
    for mesh in meshes:
        verts, faces, normals = crease_normals(mesh.vertices, mesh.faces)
        if len(faces) == 0:
            logger.warning("glTF export: mesh %r has no faces of non-zero area; left out", mesh.name)
            continue
        pos = buf.add(verts.astype("<f4"), _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True)
        nrm = buf.add(normals.astype("<f4"), _FLOAT, "VEC3", _ARRAY_BUFFER)
        index_type = ("<u2", _UINT16) if len(verts) < 0xFFFF else ("<u4", _UINT32)  # the max value is reserved
        idx = buf.add(faces.reshape(-1).astype(index_type[0]), index_type[1], "SCALAR", _ELEMENT_ARRAY_BUFFER)
        rgb = srgb_to_linear(np.asarray(mesh.color, dtype=np.float64) / 255.0)
        opacity = float(np.clip(mesh.opacity, 0.0, 1.0))
        material: dict[str, object] = {
            "name": mesh.name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [*(float(c) for c in rgb), opacity],
                "metallicFactor": 0.0,
                "roughnessFactor": 0.8,
            },
            "doubleSided": True,
        }
        if opacity < 1.0:
            material["alphaMode"] = "BLEND"
        materials.append(material)
        primitive = {
            "attributes": {"POSITION": pos, "NORMAL": nrm},
            "indices": idx,
            "material": len(materials) - 1,
            "mode": _TRIANGLES,
        }
        gltf_meshes.append({"name": mesh.name, "primitives": [primitive]})
    points_material: int | None = None
    for cloud in clouds:
        pts = np.asarray(cloud.points, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            continue
        if points_material is None:
            materials.append(
                {
                    "name": "points",
                    "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0},
                    "extensions": {"KHR_materials_unlit": {}},
                }
            )
            points_material = len(materials) - 1
        cols = srgb_to_linear(np.asarray(cloud.colors, dtype=np.float64).reshape(-1, 3) / 255.0)
        pos = buf.add(pts.astype("<f4"), _FLOAT, "VEC3", _ARRAY_BUFFER, bounds=True)
        col = buf.add(cols.astype("<f4"), _FLOAT, "VEC3", _ARRAY_BUFFER)
        primitive = {"attributes": {"POSITION": pos, "COLOR_0": col}, "material": points_material, "mode": _POINTS}
        gltf_meshes.append({"name": cloud.name, "primitives": [primitive]})
    root: dict[str, object] = {
        "name": "world",
        "rotation": _ROOT_ROTATION_XYZW,
        "extras": {"note": "children are in the z-up world frame, metres; this node turns z-up into glTF's y-up"},
    }
    nodes: list[dict[str, object]] = [root]
    for i, gm in enumerate(gltf_meshes):
        nodes.append({"name": gm["name"], "mesh": i})
    if len(nodes) > 1:
        root["children"] = list(range(1, len(nodes)))
    document: dict[str, object] = {
        "asset": {"version": "2.0", "generator": generator},
        "scene": 0,
        "scenes": [{"name": "twin", "nodes": [0]}],
        "nodes": nodes,
    }
    if gltf_meshes:
        document["meshes"] = gltf_meshes
        document["materials"] = materials
        document["accessors"] = buf.accessors
        document["bufferViews"] = buf.views
        document["buffers"] = [{"byteLength": len(buf.data)}]
    if points_material is not None:
        document["extensionsUsed"] = ["KHR_materials_unlit"]
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), _CHUNK_JSON) + text
    if buf.data:
        chunks += struct.pack("<II", len(buf.data), _CHUNK_BIN) + bytes(buf.data)
    return struct.pack("<III", _GLB_MAGIC, 2, 12 + len(chunks)) + chunks
