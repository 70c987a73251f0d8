"""Rotation inside symmetric families refined on the silhouette (issue 16 item 3).

A hexagonal nut seen from above, a square plate or a hex standoff shows nearly the same surface whatever its turn
about its symmetry axis within one period: the depth surface barely constrains that rotation, so ICP leaves it where
the hypothesis put it (the issue measured 7.8 deg median on nuts). Its outline does: a corner turned off the part
lies over the background (the sensor sees through it) and a corner the part has is left unexplained. This module
scores turns about the axis of the template's discrete rotation group (order >= 3) by the depth evidence of the
pose's whole visible surface (`kernels.depth_evidence`: supported samples minus 3 x seen-through samples) and keeps
the best turn, within half a period, when it is clearly better.
"""

from __future__ import annotations

import numpy as np

from normpos_grasp.records.template import Template
from normpos_grasp.templates import kernels
from normpos_grasp.templates.prepared import PreparedTemplate
from normpos_grasp.typing import FloatArray


def symmetry_axis(template: Template) -> tuple[FloatArray, float] | None:
    """(axis (3,) in the object frame, period radians) of the template's discrete rotation of order >= 3 with the
    smallest angle, or None (no such rotation: a continuous axis, or only half turns)."""
    best: tuple[FloatArray, float] | None = None
    for t in template.symmetry.discrete:
        r = np.asarray(t, dtype=np.float64)[:3, :3]
        ang = float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))
        if ang < np.deg2rad(1.0) or ang > np.deg2rad(121.0):
            continue
        axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
        axis /= max(float(np.linalg.norm(axis)), 1e-12)
        if best is None or ang < best[1]:
            best = (axis, ang)
    return best


def _evidence(prep: PreparedTemplate, cfo: FloatArray, k: FloatArray, depth: FloatArray, tol: float) -> float:
    pv, nv = kernels.visible_points(prep.samples, prep.normals, np.ascontiguousarray(cfo), 1.0, prep.spacing)
    if len(pv) == 0:
        return -np.inf
    uv = kernels.project_pinhole(pv, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    sup, den, vio, _mis, ng, _occ = kernels.depth_evidence(pv, nv, uv, depth, tol, 0)
    return float(sup / max(den, 1) - 3.0 * vio / max(ng, 1))


def refine_turn(
    template: Template,
    prep: PreparedTemplate,
    camera_from_object: FloatArray,
    camera_k: FloatArray,
    depth_m: FloatArray,
    tol_m: float,
    step_deg: float = 1.0,
    min_gain: float = 0.01,
) -> tuple[FloatArray, float]:
    """The pose turned about the template's symmetry axis (through its centroid) within +- half a period in
    `step_deg` steps to the best depth evidence; (camera_from_object, turn in radians), the turn 0 when no turn
    beats the pose by `min_gain` or the template has no such axis. depth_m: (H, W) metres; tol_m: support distance."""
    found = symmetry_axis(template)
    cfo = np.asarray(camera_from_object, dtype=np.float64)
    if found is None:
        return cfo, 0.0
    axis, period = found
    depth = np.ascontiguousarray(depth_m, dtype=np.float64)
    k = np.asarray(camera_k, dtype=np.float64)
    base = _evidence(prep, cfo, k, depth, tol_m)
    best, best_turn = base, 0.0
    c = prep.centroid
    for turn in np.deg2rad(np.arange(-np.rad2deg(period) / 2, np.rad2deg(period) / 2 + 1e-9, step_deg)):
        if abs(turn) < 1e-12:
            continue
        rot = _axis_angle(axis, float(turn))
        obj_turn = np.eye(4)
        obj_turn[:3, :3] = rot
        obj_turn[:3, 3] = c - rot @ c
        e = _evidence(prep, cfo @ obj_turn, k, depth, tol_m)
        if e > best:
            best, best_turn = e, float(turn)
    if best < base + min_gain or best_turn == 0.0:
        return cfo, 0.0
    rot = _axis_angle(axis, best_turn)
    obj_turn = np.eye(4)
    obj_turn[:3, :3] = rot
    obj_turn[:3, 3] = c - rot @ c
    return cfo @ obj_turn, best_turn


def _axis_angle(axis: FloatArray, angle: float) -> FloatArray:
    kx = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.asarray(np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx), dtype=np.float64)
