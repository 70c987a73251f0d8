"""DepthSegmenter on analytic height maps (table, touching blocks of different heights and tilts) and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.errors import InputError
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.perception.depth_segmenter import DepthSegmenter, DepthSegmenterOptions, ransac_plane
from normpos_grasp.training.metrics import mask_iou_matrix

W, H, F, Z0 = 640, 480, 615.0, 0.70


def _camera() -> Camera:
    return Camera(K=np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1]]), width=W, height=H)


def _frame(height: np.ndarray, noise_m: float = 0.0, seed: int = 0, tilt_x: float = 0.0) -> RGBDFrame:
    """Camera looking straight down from Z0 above a table; `height` (H, W) metres above the table per pixel; the
    table itself tilted by tilt_x (depth grows tilt_x metres per metre of x)."""
    u = (np.arange(W) - W / 2) / F
    depth = Z0 - height + tilt_x * u[None, :] * Z0
    depth = depth + np.random.default_rng(seed).normal(0.0, noise_m, depth.shape)
    return RGBDFrame(rgb=np.zeros((H, W, 3), np.uint8), depth_m=depth, camera=_camera())


def _rect(height: np.ndarray, u0: int, v0: int, u1: int, v1: int, h: float | np.ndarray) -> np.ndarray:
    m = np.zeros(height.shape, bool)
    m[v0:v1, u0:u1] = True
    height[m] = h if np.isscalar(h) else np.asarray(h)[m]
    return m


def _best_iou(found: list[np.ndarray], truth: list[np.ndarray]) -> np.ndarray:
    return mask_iou_matrix(truth, found).max(axis=1) if found else np.zeros(len(truth))


def test_implements_segmenter() -> None:
    assert isinstance(DepthSegmenter(), Segmenter)


@pytest.mark.parametrize("noise", [0.0, 0.0015])
def test_separated_and_touching_blocks_of_different_height(noise: float) -> None:
    hm = np.zeros((H, W))
    truth = [
        _rect(hm, 100, 100, 160, 160, 0.04),  # alone
        _rect(hm, 300, 200, 360, 260, 0.03),  # touching the next one, 15 mm lower
        _rect(hm, 360, 200, 420, 260, 0.045),
        _rect(hm, 200, 330, 300, 360, 0.025),  # a bar
    ]
    inst = DepthSegmenter().segment(_frame(hm, noise))
    ious = _best_iou([i.mask for i in inst], truth)
    assert (ious > 0.8).all(), ious
    assert len(inst) == 4
    assert [i.instance_id for i in inst] == [1, 2, 3, 4]
    assert all(i.label == "" for i in inst)


def test_touching_blocks_of_same_height_different_normal() -> None:
    """A flat block and a block whose top is tilted 40 degrees, touching, meeting at the same height."""
    hm = np.zeros((H, W))
    flat = _rect(hm, 250, 200, 320, 280, 0.05)
    u = np.arange(W)[None, :].repeat(H, 0)
    ramp = 0.05 + np.tan(np.radians(40)) * (u - 320) * Z0 / F  # rising away from the flat block
    tilted = _rect(hm, 320, 200, 370, 280, ramp)
    inst = DepthSegmenter().segment(_frame(hm, 0.001))
    ious = _best_iou([i.mask for i in inst], [flat, tilted])
    assert (ious > 0.7).all(), ious


def test_tilted_table_is_removed() -> None:
    hm = np.zeros((H, W))
    block = _rect(hm, 280, 200, 340, 260, 0.03)
    inst = DepthSegmenter().segment(_frame(hm, 0.001, tilt_x=0.3))
    assert len(inst) == 1
    assert _best_iou([i.mask for i in inst], [block])[0] > 0.8


def test_empty_table_and_invalid_depth_give_no_instances() -> None:
    seg = DepthSegmenter()
    assert seg.segment(_frame(np.zeros((H, W)), 0.001)) == []
    f = _frame(np.zeros((H, W)))
    for bad in (np.zeros((H, W)), np.full((H, W), np.nan)):
        assert seg.segment(RGBDFrame(rgb=f.rgb, depth_m=bad, camera=f.camera)) == []


def test_min_size_filter_and_options() -> None:
    hm = np.zeros((H, W))
    _rect(hm, 100, 100, 108, 108, 0.03)  # 64 px: below the default 150
    assert DepthSegmenter().segment(_frame(hm)) == []
    with pytest.raises(InputError):
        DepthSegmenterOptions(stride=0)
    with pytest.raises(InputError):
        DepthSegmenter().segment("frame")  # type: ignore[arg-type]


def test_ransac_plane_recovers_plane_with_outliers() -> None:
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.3, 0.3, (3000, 2))
    n_true = np.array([0.1, -0.2, -1.0]) / np.linalg.norm([0.1, -0.2, -1.0])
    d_true = 0.8
    z = -(n_true[0] * xy[:, 0] + n_true[1] * xy[:, 1] + d_true) / n_true[2]
    pts = np.column_stack([xy, z])
    pts[:800, 2] -= rng.uniform(0.02, 0.1, 800)  # objects above the plane
    n, d, support = ransac_plane(pts, 0.002, 64, 2048, np.random.default_rng(0))
    assert d > 0
    sign = np.sign(n @ n_true)
    np.testing.assert_allclose(n * sign, n_true, atol=2e-3)
    assert support > 0.6 * 2048
