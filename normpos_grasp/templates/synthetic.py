"""Synthetic views of posed templates for self-checks, tests and benchmarks (ray-cast, D435-like noise).

`render_views` ray-casts posed templates into a camera, adds depth noise RMS = noise_per_m2 * z^2
(D435: 0.0036 / m, see reference/sensor_noise.md) and returns the noisy depth image with one
`NormPosition` per visible object (camera frame), built the way the measurement stage builds them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.camera.render import render
from normpos_grasp.records.kinds import Frame
from normpos_grasp.records.normpos import NormPosition, OrientedBox
from normpos_grasp.records.template import Template
from normpos_grasp.typing import FloatArray


@dataclass(frozen=True, eq=False)
class SyntheticView:
    """depth_m (H, W) noisy metric depth; normpos: per posed template (None-free: objects hidden below
    `min_pixels` are dropped and `visible` says which were kept); visible_fraction per kept object."""

    depth_m: FloatArray
    normpos: tuple[NormPosition, ...]
    kept: tuple[int, ...]
    visible_fraction: tuple[float, ...]


def render_views(
    camera: Camera,
    objects: Sequence[tuple[Template, FloatArray]],
    rng: np.random.Generator,
    *,
    noise_per_m2: float = 0.0036,
    min_pixels: int = 50,
    label: bool = True,
    extra_meshes: Sequence[tuple[object, FloatArray]] = (),
    true_normals: bool = False,
) -> SyntheticView:
    """Render `objects` [(template, camera_from_object)] plus `extra_meshes` (e.g. a table) into `camera`.

    Normals are estimated from the noisy points (as the measurement stage does) unless `true_normals`.
    """
    meshes = [(t.mesh, p) for t, p in objects] + list(extra_meshes)
    rend = render(camera, meshes)
    depth = rend.depth_m.copy()
    valid = depth > 0
    depth[valid] += rng.normal(size=int(valid.sum())) * noise_per_m2 * depth[valid] ** 2
    nps = []
    kept = []
    fracs = []
    for k, (t, pose) in enumerate(objects):
        mask = rend.index == k
        if int(mask.sum()) < min_pixels:
            continue
        alone = render(camera, [(t.mesh, pose)])
        full = int((alone.depth_m > 0).sum())
        fracs.append(float(mask.sum()) / max(full, 1))
        v, u = np.nonzero(mask)
        pix = np.column_stack([u, v]).astype(np.int64)
        pts = camera.backproject(pix, depth[v, u])
        if true_normals:
            nrm = rend.normals_camera[v, u]
        else:
            from normpos_grasp.templates.fit import estimate_normals

            nrm = estimate_normals(pts, np.zeros(3))
        nps.append(make_normpos(pts, nrm, pix, mask, t.label if label else "", k + 1))
        kept.append(k)
    return SyntheticView(depth, tuple(nps), tuple(kept), tuple(fracs))


def make_normpos(
    points: FloatArray,
    normals: FloatArray,
    pixels: np.ndarray,
    mask: np.ndarray,
    label: str,
    instance_id: int,
    frame: Frame = "camera",
    viewpoint: FloatArray | None = None,
) -> NormPosition:
    """A `NormPosition` from measured points (camera frame unless `frame`/`viewpoint` say otherwise)."""
    c = points.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((points - c).T)) if len(points) > 3 else (np.ones(3), np.eye(3))
    axes = v[:, np.argsort(w)[::-1]]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    local = (points - c) @ axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    obb = OrientedBox(center=c + axes @ ((lo + hi) / 2), axes=axes, extents=hi - lo)
    return NormPosition(
        label=label,
        score=1.0,
        mask=mask,
        points=points,
        normals=normals,
        pixels=np.asarray(pixels, dtype=np.int64),
        frame=frame,
        viewpoint=np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64),
        instance_id=instance_id,
        centroid=c,
        aabb_min=points.min(axis=0),
        aabb_max=points.max(axis=0),
        obb=obb,
    )
