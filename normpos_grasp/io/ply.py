"""Point-cloud PLY files (vertices only): x y z as float64, optional normals (float32) and RGB colours (uint8).

Written in binary little-endian; read back in binary or ASCII. Units are whatever the caller uses (the
library writes metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from normpos_grasp.errors import DatasetError, InputError
from normpos_grasp.typing import ArrayLike, FloatArray, UInt8Array

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
