"""PLY files: point clouds (vertices only) and triangle meshes (BOP object models).

Point clouds: x y z as float64, optional normals (float32) and RGB colours (uint8). Meshes: float32 x y z and
nx ny nz, faces as `property list uchar int vertex_indices` with exactly three corners each and no other face
property, the layout the BOP toolkit's PLY reader accepts. Written in binary little-endian; point clouds read
back in binary or ASCII. Units are whatever the caller uses (point clouds in metres, BOP models in mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from normpos_grasp.errors import DatasetError, InputError
from normpos_grasp.typing import ArrayLike, FloatArray, IntArray, UInt8Array

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip


@dataclass(frozen=True, eq=False)
class PointCloud:
    """points (N, 3) float64; normals (N, 3) float64 or None; colors (N, 3) uint8 or None."""

    points: FloatArray
    normals: FloatArray | None = None
    colors: UInt8Array | None = None


def write_ply(
    path: str | Path, points: ArrayLike, normals: ArrayLike | None = None, colors: ArrayLike | None = None
) -> None:
    """Write (N, 3) points [+ (N, 3) normals, (N, 3) uint8 colours] as binary PLY, atomically."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must be (N, 3), got {pts.shape}")
    fields: list[tuple[str, str]] = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    header_props = ["property double x", "property double y", "property double z"]
    nrm = None
    col = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float32)
        if nrm.shape != pts.shape:
            raise InputError(f"normals must be {pts.shape} like the points, got {nrm.shape}")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        header_props += ["property float nx", "property float ny", "property float nz"]
    if colors is not None:
        col = np.asarray(colors)
        if col.shape != pts.shape or col.dtype != np.uint8:
            raise InputError(f"colors must be uint8 {pts.shape}, got {col.dtype} {col.shape}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header_props += ["property uchar red", "property uchar green", "property uchar blue"]
    data = np.empty(len(pts), dtype=np.dtype(fields))
    data["x"], data["y"], data["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if nrm is not None:
        data["nx"], data["ny"], data["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    if col is not None:
        data["red"], data["green"], data["blue"] = col[:, 0], col[:, 1], col[:, 2]
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", f"element vertex {len(pts)}", *header_props, "end_header"]
    )
    target = Path(path)
    tmp = target.with_name(target.name + ".tmp")
    tmp.write_bytes(header.encode("ascii") + b"\n" + data.tobytes())
    tmp.replace(target)


def triangulate_faces(faces: ArrayLike | Sequence[Sequence[int]]) -> IntArray:
    """(T, 3) triangles from faces given as an (M, k) array (k >= 3) or a list of index lists of any length >= 3:
    each polygon is split into a fan from its first corner, right for the convex polygons (quads, n-gons) that
    mesh formats store; the corner order, and so the facing, is kept."""
    try:
        rows = [np.asarray(faces, dtype=np.int64)]
        if rows[0].size == 0:
            return np.zeros((0, 3), dtype=np.int64)
    except ValueError:  # ragged: polygons of different lengths
        rows = [np.asarray(f, dtype=np.int64).reshape(1, -1) for f in faces]  # type: ignore[union-attr]
    triangles: list[IntArray] = []
    for block in rows:
        if block.ndim != 2 or block.shape[1] < 3:
            raise InputError(f"faces need at least 3 vertex indices each, got shape {block.shape}")
        k = np.arange(1, block.shape[1] - 1)
        fan = np.stack([np.repeat(block[:, :1], len(k), axis=1), block[:, k], block[:, k + 1]], axis=-1)
        triangles.append(fan.reshape(-1, 3))
    return np.vstack(triangles)


def write_mesh_ply(
    path: str | Path,
    vertices: ArrayLike,
    faces: ArrayLike | Sequence[Sequence[int]],
    normals: ArrayLike | None = None,
    comment: str = "normpos-grasp",
) -> None:
    """Write a triangle mesh as binary little-endian PLY, atomically.

    vertices (N, 3) and optional per-vertex normals (N, 3) are written as float32; faces (see `triangulate_faces`:
    triangles, quads or polygons) as triangles only, `property list uchar int vertex_indices`.
    """
    verts = np.asarray(vertices, dtype=np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3 or not np.all(np.isfinite(verts)):
        raise InputError(f"vertices must be finite (N, 3), got shape {verts.shape}")
    tris = triangulate_faces(faces)
    if len(tris) and (tris.min() < 0 or tris.max() >= len(verts)):
        raise InputError(f"face indices must lie in 0..{len(verts) - 1}, got {tris.min()}..{tris.max()}")
    if len(verts) > np.iinfo(np.int32).max:
        raise InputError(f"{len(verts)} vertices do not fit PLY int indices")
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = [
        "ply",
        "format binary_little_endian 1.0",
        f"comment {comment}",
        f"element vertex {len(verts)}",
        "property float x",
        "property float y",
        "property float z",
    ]
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != verts.shape or not np.all(np.isfinite(nrm)):
            raise InputError(f"normals must be finite {verts.shape} like the vertices, got {nrm.shape}")
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        header += ["property float nx", "property float ny", "property float nz"]
    header += [f"element face {len(tris)}", "property list uchar int vertex_indices", "end_header"]
    vertex_data = np.empty(len(verts), dtype=np.dtype(fields))
    vertex_data["x"], vertex_data["y"], vertex_data["z"] = verts.T
    if normals is not None:
        vertex_data["nx"], vertex_data["ny"], vertex_data["nz"] = nrm.T
    face_data = np.empty(len(tris), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))  # packed: 13 bytes
    face_data["n"] = 3
    face_data["v"] = tris
    target = Path(path)
    tmp = target.with_name(target.name + ".tmp")
    tmp.write_bytes("\n".join(header).encode("ascii") + b"\n" + vertex_data.tobytes() + face_data.tobytes())
    tmp.replace(target)


def read_ply(path: str | Path) -> PointCloud:
    """Read the vertex element of a PLY (binary little/big endian or ASCII); faces are ignored."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise DatasetError(f"cannot read {p}: {exc}") from exc
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DatasetError(f"{p} is not a PLY file (no 'ply' magic or end_header)")
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = ""
    n_vertex = -1
    props: list[tuple[str, str]] = []
    current = ""
    first_element = ""
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            current = parts[1]
            first_element = first_element or current
            if current == "vertex":
                n_vertex = int(parts[2])
        elif parts[0] == "property" and current == "vertex":
            if parts[1] == "list":
                raise DatasetError(f"{p}: list properties on vertices are not supported")
            if parts[1] not in _PLY_TYPES:
                raise DatasetError(f"{p}: unknown PLY type {parts[1]!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if n_vertex < 0 or first_element != "vertex":
        raise DatasetError(f"{p}: the vertex element must come first")
    names = [n for n, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(f"{p}: vertices lack x, y, z")
    if fmt == "ascii":
        rows = raw[body_start:].decode("ascii").split("\n")[:n_vertex]
        table = np.array([r.split()[: len(props)] for r in rows], dtype=np.float64).reshape(n_vertex, len(props))
        cols = {n: table[:, i] for i, n in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(n, order + t) for n, t in props])
        if len(raw) - body_start < dt.itemsize * n_vertex:
            raise DatasetError(f"{p}: truncated, expected {n_vertex} vertices")
        arr = np.frombuffer(raw, dtype=dt, count=n_vertex, offset=body_start)
        cols = {n: arr[n] for n in names}
    else:
        raise DatasetError(f"{p}: unsupported PLY format {fmt!r}")
    pts = np.column_stack([cols["x"], cols["y"], cols["z"]]).astype(np.float64)
    normals = None
    if {"nx", "ny", "nz"} <= set(names):
        normals = np.column_stack([cols["nx"], cols["ny"], cols["nz"]]).astype(np.float64)
    colors = None
    if {"red", "green", "blue"} <= set(names):
        colors = np.column_stack([cols["red"], cols["green"], cols["blue"]]).astype(np.uint8)
    return PointCloud(pts, normals, colors)
