"""Ray-cast rendering of posed meshes into a camera: metric depth and per-pixel object index.

Used to make ground-truth masks (for example from BOP poses) and noise-free synthetic depth for tests and
benchmarks. Rays go through pixel centres (undistorted when the camera has distortion), so a rendered
depth back-projects exactly onto the mesh surface.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import InputError, MeshError
from normpos_grasp.geometry.transforms import transform_points
from normpos_grasp.typing import BoolArray, FloatArray, IntArray
from normpos_grasp.validation import check_pose

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Rendering:
    """Result of `render`: depth_m (H, W) z-depth in metres (0 = no surface), index (H, W) int64 (-1 = none,
    k = k-th mesh), normals_camera (H, W, 3) unit surface normals in the camera frame (0 where none)."""

    depth_m: FloatArray
    index: IntArray
    normals_camera: FloatArray

    def mask(self, k: int) -> BoolArray:
        """(H, W) bool visible mask of mesh `k`."""
        return np.asarray(self.index == k)


def render(camera: Camera, meshes: Sequence[tuple[Any, FloatArray]]) -> Rendering:
    """Ray-cast `meshes` [(trimesh.Trimesh in metres, camera_from_object (4, 4))] into `camera`.

    Each pixel holds the nearest surface along its ray; `render_silhouettes` gives unoccluded masks.
    """
    import trimesh

    h, w = camera.height, camera.width
    depth = np.zeros((h, w))
    index = np.full((h, w), -1, dtype=np.int64)
    normals = np.zeros((h, w, 3))
    if not meshes:
        return Rendering(depth, index, normals)
    parts = []
    owner = []
    for k, (mesh, pose) in enumerate(meshes):
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise MeshError(f"mesh {k} must be a non-empty trimesh.Trimesh, got {type(mesh).__name__}")
        cfo = check_pose(pose, f"camera_from_object[{k}]", 1e-5)
        verts = transform_points(cfo, np.asarray(mesh.vertices, dtype=np.float64))
        parts.append(trimesh.Trimesh(verts, np.asarray(mesh.faces), process=False))
        owner.append(np.full(len(mesh.faces), k, dtype=np.int64))
    scene: Any = trimesh.util.concatenate(parts) if len(parts) > 1 else parts[0]
    face_owner = np.concatenate(owner)
    verts = np.asarray(scene.vertices)
    front = verts[verts[:, 2] > 1e-6]
    if front.size == 0:
        return Rendering(depth, index, normals)
    if np.all(verts[:, 2] > 1e-6):
        px = camera.project(verts)
        u0, v0 = np.floor(px.min(axis=0)).astype(int) - 1
        u1, v1 = np.ceil(px.max(axis=0)).astype(int) + 1
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, w - 1), min(v1, h - 1)
    else:  # mesh crosses the image plane: cast every pixel
        u0, v0, u1, v1 = 0, 0, w - 1, h - 1
    if u1 < u0 or v1 < v0:
        return Rendering(depth, index, normals)
    vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
    xy = camera.normalized_coordinates(np.column_stack([uu.ravel(), vv.ravel()]))
    dirs = np.column_stack([xy, np.ones(len(xy))])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.zeros_like(dirs)
    locations, ray_idx, tri_idx = scene.ray.intersects_location(origins, dirs, multiple_hits=False)
    if len(ray_idx) == 0:
        return Rendering(depth, index, normals)
    # keep the nearest hit per ray (some back-ends may return more than one)
    z = locations[:, 2]
    order = np.lexsort((z, ray_idx))
    ray_idx, tri_idx, z = ray_idx[order], tri_idx[order], z[order]
    first = np.ones(len(ray_idx), dtype=bool)
    first[1:] = ray_idx[1:] != ray_idx[:-1]
    ray_idx, tri_idx, z = ray_idx[first], tri_idx[first], z[first]
    keep = z > 0
    ray_idx, tri_idx, z = ray_idx[keep], tri_idx[keep], z[keep]
    rows = vv.ravel()[ray_idx]
    cols = uu.ravel()[ray_idx]
    depth[rows, cols] = z
    index[rows, cols] = face_owner[tri_idx]
    fn = np.asarray(scene.face_normals)[tri_idx]
    flip = np.einsum("ij,ij->i", fn, dirs[ray_idx]) > 0
    fn[flip] *= -1.0
    normals[rows, cols] = fn
    return Rendering(depth, index, normals)


def render_silhouettes(camera: Camera, meshes: Sequence[tuple[Any, FloatArray]]) -> list[BoolArray]:
    """Full (unoccluded) silhouette of each mesh alone, as (H, W) bool masks."""
    if not meshes:
        raise InputError("render_silhouettes needs at least one mesh")
    return [render(camera, [m]).index == 0 for m in meshes]


def visible_mask(depth_model_m: FloatArray, depth_measured_m: FloatArray, delta_m: float = 0.015) -> BoolArray:
    """BOP's visibility test (bop19 mode): pixels where the rendered model exists and is not hidden.

    A pixel of the rendered object is visible when the measured depth is missing (0 / non-finite) or lies
    no more than `delta_m` metres in front of the rendered surface. Shapes (H, W); returns bool (H, W).
    """
    model = np.asarray(depth_model_m, dtype=np.float64)
    test = np.asarray(depth_measured_m, dtype=np.float64)
    if model.shape != test.shape:
        raise InputError(f"rendered {model.shape} and measured {test.shape} depth images differ in shape")
    if not delta_m >= 0:
        raise InputError(f"delta_m must be >= 0 metres, got {delta_m}")
    missing = ~np.isfinite(test) | (test <= 0)
    with np.errstate(invalid="ignore"):
        close = (model - test) <= delta_m
    return np.asarray((model > 0) & (missing | close))
