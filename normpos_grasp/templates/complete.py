"""The completed norm-position: every surface point of a fitted template in the measurement frame.

The paper's resolution method 2: once the template is fitted, ALL its surface points (hidden sides
included) are known; each is marked measured (a measured point lies within the inlier distance) or inferred.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from normpos_grasp.errors import InputError
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.templates.prepared import prepare
from normpos_grasp.typing import BoolArray, FloatArray


@dataclass(frozen=True, eq=False)
class CompletedNormPosition:
    """points (M, 3) and outward normals (M, 3) of the whole fitted surface in `frame`, metres;
    measured (M,) True where a measured point supports the surface point, False where inferred;
    label / instance_id from the fit; fit: the `TemplateFit` used."""

    label: str
    instance_id: int
    frame: str
    points: FloatArray
    normals: FloatArray
    measured: BoolArray
    fit: TemplateFit

    @property
    def measured_share(self) -> float:
        return float(self.measured.mean()) if len(self.measured) else 0.0


def complete_normposition(
    fit: TemplateFit,
    normpos: NormPosition | None = None,
    *,
    tolerance_m: float = 0.004,
) -> CompletedNormPosition:
    """Surface samples of `fit.template` posed by `fit` (size factor applied), split measured/inferred.

    Without `normpos` every point is marked inferred. Raises InputError for a rejected fit (its pose is not
    trustworthy).
    """
    if not fit.accepted:
        raise InputError(f"cannot complete a rejected fit ({fit.reason}); use an accepted TemplateFit")
    prep = prepare(fit.template)
    rot = fit.frame_from_object[:3, :3]
    pts = (prep.samples * fit.scale) @ rot.T + fit.frame_from_object[:3, 3]
    nrm = prep.normals @ rot.T
    measured = np.zeros(len(pts), dtype=bool)
    if normpos is not None and normpos.n_points:
        if normpos.frame != fit.frame:
            raise InputError(f"norm-position frame '{normpos.frame}' differs from the fit's frame '{fit.frame}'")
        d, _ = cKDTree(np.asarray(normpos.points, dtype=np.float64)).query(pts, distance_upper_bound=tolerance_m)
        measured = np.isfinite(d)
    return CompletedNormPosition(
        label=fit.template.label,
        instance_id=fit.instance_id,
        frame=fit.frame,
        points=pts,
        normals=nrm,
        measured=measured,
        fit=fit,
    )
