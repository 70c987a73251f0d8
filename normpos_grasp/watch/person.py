"""A shape rule for person-sized intruders (no learned model, nothing downloaded).

A blob's world points are reduced to their extents along the two principal axes of the horizontal plane and its
height span. A blob at least `min_major_m` long and `min_minor_m` wide (a torso, shoulders, a head with an arm
seen from above) is a 'person'; one at least `min_hand_m` across is a 'hand' (a hand, forearm or tool held in
it); anything smaller is an 'object'. The camera sees only the near side of what enters, so the rule names what
is visible: a person whose arm alone reaches into the view is a 'hand'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.typing import FloatArray


@dataclass(frozen=True)
class PersonRule:
    """Extents in metres: min_major_m / min_minor_m for a person, min_hand_m for a hand."""

    min_major_m: float = 0.35
    min_minor_m: float = 0.15
    min_hand_m: float = 0.04


def blob_extent(points_world: FloatArray) -> tuple[float, float, float]:
    """(major, minor, height) extent of (N, 3) points, m: horizontal principal axes (5-95 % span) and z span."""
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3:
        return 0.0, 0.0, 0.0
    xy = p[:, :2] - p[:, :2].mean(axis=0)
    _, vecs = np.linalg.eigh(xy.T @ xy)
    spans = []
    for axis in (vecs[:, 1], vecs[:, 0]):
        s = xy @ axis
        lo, hi = np.percentile(s, [5, 95])
        spans.append(float(hi - lo))
    zlo, zhi = np.percentile(p[:, 2], [5, 95])
    return spans[0], spans[1], float(zhi - zlo)


def classify(points_world: FloatArray, rule: PersonRule | None = None) -> str:
    """'person', 'hand' or 'object' for one blob's world points (N, 3)."""
    r = PersonRule() if rule is None else rule
    major, minor, _ = blob_extent(points_world)
    if major >= r.min_major_m and minor >= r.min_minor_m:
        return "person"
    if max(major, minor) >= r.min_hand_m:
        return "hand"
    return "object"
