"""Control-point pose fitting (the paper's Eq. 11-16) and control-point detection on measured points.

`fit_control_points` aligns named template control points with measured ones by Kabsch, enumerating the
template's symmetries (a symmetric part's corners can be labelled in several equivalent ways) and keeping
the assignment with the smallest residual. `control_point_hypotheses` detects candidate points on a
measurement (OBB corners, extremal points along the principal axes) and matches them to the template's
control points by edge-length-consistent triples: each consistent triple is a pose hypothesis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.geometry.kabsch import kabsch
from normpos_grasp.records.template import Template
from normpos_grasp.templates import kernels
from normpos_grasp.templates.features import batched_kabsch
from normpos_grasp.typing import ArrayLike, FloatArray


@dataclass(frozen=True, eq=False)
class ControlPointFit:
    """frame_from_object (4, 4); rmse_m of the control points; symmetry_index: which symmetry relabelling won."""

    frame_from_object: FloatArray
    rmse_m: float
    symmetry_index: int
    names: tuple[str, ...]


def fit_control_points(template: Template, measured: dict[str, ArrayLike]) -> ControlPointFit:
    """Kabsch fit of named control points (metres, measurement frame) to the template's.

    Raises:
        InputError: fewer than 3 names shared with the template, or collinear points.
    """
    names = tuple(n for n in measured if n in template.control_points)
    if len(names) < 3:
        raise InputError(
            f"control-point fit needs at least 3 named points shared with template '{template.name}'; "
            f"got {sorted(measured)}, template has {sorted(template.control_points)}"
        )
    src = np.array([template.control_points[n] for n in names], dtype=np.float64)
    dst = np.array([np.asarray(measured[n], dtype=np.float64).reshape(3) for n in names])
    best: ControlPointFit | None = None
    for k, sym in enumerate(template.symmetry.transforms(continuous_steps=36)):
        s = src @ sym[:3, :3].T + sym[:3, 3]
        pose = kabsch(s, dst) @ sym  # frame_from_object: relabelled points map through the symmetry
        res = dst - (src @ pose[:3, :3].T + pose[:3, 3])
        rmse = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
        if best is None or rmse < best.rmse_m - 1e-12:
            best = ControlPointFit(pose, rmse, k, names)
    if best is None:  # transforms() always holds the identity
        raise InputError("template symmetry produced no transforms")
    return best


def detect_control_points(points: FloatArray) -> FloatArray:
    """(K, 3) candidate control points of a measured cloud: OBB corners (8) and extremal points (6)."""
    c = points.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((points - c).T))
    axes = v[:, np.argsort(w)[::-1]]
    local = (points - c) @ axes
    lo, hi = local.min(axis=0), local.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    ext = [points[np.argmin(local[:, i])] for i in range(3)] + [points[np.argmax(local[:, i])] for i in range(3)]
    return np.vstack([corners @ axes.T + c, np.array(ext)])


def control_point_hypotheses(
    template: Template,
    points: FloatArray,
    viewpoint: FloatArray,
    diameter: float,
    *,
    n_samples: int = 400,
    seed: int = 7,
) -> FloatArray:
    """(H, 4, 4) `object_from_frame` hypotheses from detected points matched to template control points."""
    cps = np.array(list(template.control_points.values()), dtype=np.float64).reshape(-1, 3)
    if len(cps) < 3 or len(points) < 10:
        return np.zeros((0, 4, 4))
    det = detect_control_points(points)
    rng = np.random.default_rng(seed)
    di = rng.integers(0, len(det), size=(n_samples, 3))
    ti = rng.integers(0, len(cps), size=(n_samples, 3))
    a = det[di]
    b = cps[ti]
    ok = np.flatnonzero(kernels.consistent_triples(a, b, 0.05 * diameter + 0.003, 0.2 * diameter, di, False))[:24]
    if len(ok) == 0:
        return np.zeros((0, 4, 4))
    return batched_kabsch(a[ok], b[ok])
