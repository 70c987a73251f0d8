"""Clutter from measured points no fit explains (`planning.plan._drop_outliers`): lone points (flying pixels) are
dropped, and the points kept are exactly those with `min_points` neighbours within the radius, as counting every
point in a k-d tree gives, whether a point is kept by its cell's count or by its own count."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from normpos_grasp.planning.plan import _drop_outliers


def _reference(points: np.ndarray, radius: float, min_points: int) -> np.ndarray:
    counts = cKDTree(points).query_ball_point(points, radius, return_length=True)
    return points[np.asarray(counts) >= min_points]


def test_the_points_kept_are_those_with_enough_neighbours() -> None:
    rng = np.random.default_rng(31)
    for trial in range(25):
        # a dense measured patch (1-3 mm spacing), sparse strays around it, a few points at exactly the radius
        patch = rng.uniform([0.0, 0.0, 0.0], [0.05, 0.04, 0.002], size=(int(rng.integers(50, 800)), 3))
        strays = rng.uniform(-0.05, 0.1, size=(int(rng.integers(0, 60)), 3))
        pair = rng.uniform(-0.2, -0.1, size=(1, 3))
        ring = pair + np.array([[0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])  # two points at 1 cm from one
        pts = np.concatenate([patch, strays, pair, ring])[rng.permutation(len(patch) + len(strays) + 3)]
        for min_points in (2, 3, 5):
            got = _drop_outliers(pts, 0.01, min_points)
            assert np.array_equal(got, _reference(pts, 0.01, min_points)), (trial, min_points)


def test_lone_points_go_and_dense_points_stay() -> None:
    dense = np.stack(np.meshgrid(np.arange(10), np.arange(10), [0]), axis=-1).reshape(-1, 3) * 0.002
    lone = np.array([[1.0, 1.0, 1.0], [-1.0, 0.5, 0.2]])
    kept = _drop_outliers(np.concatenate([dense, lone]), 0.01, 3)
    assert np.array_equal(kept, dense)
    assert len(_drop_outliers(lone, 0.01, 3)) == 0
    assert np.array_equal(_drop_outliers(lone, 0.01, 1), lone)  # min_points 1: every point counts itself
