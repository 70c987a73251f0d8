"""One pose per physical object: frame-level suppression of accepted fits whose models overlap in space.

Fragments of one object (a segmenter that cut a can in three) or two templates fitted to the same points each
give an accepted fit of their own; only one of them is the object. Accepted fits are taken best-explaining
first (score x explained share of the model's visible surface); a fit whose posed model surface overlaps an
already kept one (a share of its surface samples within a distance of the kept model's surface, either way), or
whose measured points are mostly the kept one's (same pixels), is marked rejected with the reason.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.templates.prepared import prepare
from normpos_grasp.typing import FloatArray

#: posed model samples used per fit for the overlap test
_N_SAMPLES = 400


def explanation_key(fit: TemplateFit) -> float:
    """How much a fit explains, for ranking fits of one frame: score x explained share (1 when not measured)."""
    return float(fit.score) * float(fit.extra.get("explained_share", 1.0))


def _posed_samples(fit: TemplateFit) -> FloatArray:
    prep = prepare(fit.template)
    sub = prep.samples[:: max(1, len(prep.samples) // _N_SAMPLES)] * fit.scale
    pose = fit.frame_from_object
    return np.asarray(sub @ pose[:3, :3].T + pose[:3, 3], dtype=np.float64)


def model_overlap(a: TemplateFit, b: TemplateFit, distance_m: float | None = None) -> float:
    """Largest share (of either fit's posed model surface samples) lying within `distance_m` of the other's surface.

    distance_m: default max(4 mm, 5 % of the smaller template diameter). 1.0 for the same pose, 0 for disjoint models.
    """
    prep_a, prep_b = prepare(a.template), prepare(b.template)
    if distance_m is None:
        distance_m = max(0.004, 0.05 * min(prep_a.diameter, prep_b.diameter))
    ca = a.frame_from_object[:3, :3] @ (prep_a.centroid * a.scale) + a.frame_from_object[:3, 3]
    cb = b.frame_from_object[:3, :3] @ (prep_b.centroid * b.scale) + b.frame_from_object[:3, 3]
    if np.linalg.norm(ca - cb) > prep_a.diameter * a.scale + prep_b.diameter * b.scale + distance_m:
        return 0.0  # too far apart to touch
    pa, pb = _posed_samples(a), _posed_samples(b)
    da, _ = cKDTree(pb).query(pa, distance_upper_bound=distance_m)
    db, _ = cKDTree(pa).query(pb, distance_upper_bound=distance_m)
    return float(max(np.mean(np.isfinite(da)), np.mean(np.isfinite(db))))


def _pixel_overlap(a: NormPosition, b: NormPosition) -> float:
    """Share of the smaller norm-position's measured pixels that the other one also holds."""
    pa = np.asarray(a.pixels, dtype=np.int64).reshape(-1, 2)
    pb = np.asarray(b.pixels, dtype=np.int64).reshape(-1, 2)
    if len(pa) == 0 or len(pb) == 0:
        return 0.0
    ka = pa[:, 1] * 100_003 + pa[:, 0]
    kb = pb[:, 1] * 100_003 + pb[:, 0]
    return float(np.isin(ka, kb).sum()) / min(len(ka), len(kb))


def one_pose_per_object(
    fits: Sequence[TemplateFit],
    normpositions: Sequence[NormPosition] | None = None,
    min_overlap: float = 0.2,
    min_shared_pixels: float = 0.5,
) -> list[TemplateFit]:
    """`fits` (one frame, input order kept) with accepted fits that duplicate a better-explaining one rejected.

    Two accepted fits are one object when their posed models overlap (`model_overlap` >= min_overlap) or, with
    `normpositions` (matched to fits by instance_id), when they share at least `min_shared_pixels` of the
    smaller one's measured pixels. The kept fit is the one with the larger `explanation_key`.
    """
    by_id = {n.instance_id: n for n in normpositions} if normpositions is not None else {}
    order = sorted((i for i, f in enumerate(fits) if f.accepted), key=lambda i: explanation_key(fits[i]), reverse=True)
    out = list(fits)
    kept: list[int] = []
    for i in order:
        dup = None
        for j in kept:
            ov = model_overlap(fits[i], fits[j])
            if ov >= min_overlap:
                dup = (j, f"models overlap {ov:.2f}")
                break
            ni, nj = by_id.get(fits[i].instance_id), by_id.get(fits[j].instance_id)
            if ni is not None and nj is not None and ni is not nj:
                sh = _pixel_overlap(ni, nj)
                if sh >= min_shared_pixels:
                    dup = (j, f"{sh:.2f} of the measured pixels shared")
                    break
        if dup is None:
            kept.append(i)
            continue
        j, why = dup
        other = fits[j]
        out[i] = replace(
            fits[i],
            accepted=False,
            reason=f"same object as instance {other.instance_id} ('{other.template.name}', score {other.score:.3f}, "
            f"explains more): {why}",
            extra={**fits[i].extra, "duplicate_of": other.instance_id},
        )
    return out
