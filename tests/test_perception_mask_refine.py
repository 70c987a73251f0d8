"""mask_refine: soft masks snapped to depth steps and colour borders, overlaps resolved, holes filled."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from normpos_grasp.errors import InputError
from normpos_grasp.perception.mask_refine import MaskRefineOptions, SoftMask, far_edges, refine_masks

H, W = 120, 160


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def blurred(mask: np.ndarray, sigma: float, shift: tuple[int, int] = (0, 0)) -> np.ndarray:
    """A soft mask like an upsampled low-resolution prediction: the true mask shifted and blurred."""
    m = np.roll(mask.astype(np.float32), shift, axis=(0, 1))
    return cv2.GaussianBlur(m, (0, 0), sigma)


def soft_of(prob: np.ndarray, margin: int = 10) -> SoftMask:
    ys, xs = np.nonzero(prob > 0.05)
    y0, x0 = max(ys.min() - margin, 0), max(xs.min() - margin, 0)
    y1, x1 = min(ys.max() + margin + 1, H), min(xs.max() + margin + 1, W)
    return SoftMask(np.ascontiguousarray(prob[y0:y1, x0:x1]), int(x0), int(y0))


def two_blocks(floor_m: float = 0.8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth of a floor with two touching blocks of different heights; their true masks."""
    a = np.zeros((H, W), bool)
    b = np.zeros((H, W), bool)
    a[30:80, 30:75] = True
    b[40:90, 75:120] = True
    depth = np.full((H, W), floor_m)
    depth[a] = floor_m - 0.05
    depth[b] = floor_m - 0.03
    return depth, a, b


def test_depth_steps_snap_blurred_masks_to_the_true_border() -> None:
    depth, a, b = two_blocks()
    pa, pb = blurred(a, 4.0, (2, -2)), blurred(b, 4.0, (-2, 3))
    out = refine_masks([soft_of(pa), soft_of(pb)], depth, (H, W))
    assert out.shape == (2, H, W)
    assert iou(out[0], a) > 0.98 and iou(out[1], b) > 0.98
    # the plain threshold of the same soft masks is visibly worse
    assert iou(pa > 0.5, a) < 0.95 and iou(pb > 0.5, b) < 0.95


@pytest.mark.parametrize("floor_m", [0.5, 1.2, 2.0])
def test_range_relative_step_ignores_noise_but_finds_parts(floor_m: float) -> None:
    depth, a, _ = two_blocks(floor_m)
    rng = np.random.default_rng(0)
    sigma = 0.0015 * floor_m**2  # stereo noise grows with range squared
    noisy = depth + rng.normal(0.0, sigma, depth.shape)
    valid, edge, _ = far_edges(noisy, MaskRefineOptions())
    assert valid.all()
    inner = np.zeros((H, W), bool)
    inner[5:-5, 5:-5] = True
    rim = a ^ cv2.erode(a.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    border = cv2.dilate(rim.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert edge[inner & ~border].mean() < 0.01  # noise alone seldom makes an edge
    ring = cv2.dilate(a.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~a
    assert edge[ring].mean() > 0.7  # the floor pixels right beside block a are far-side edge pixels


def test_overlapping_claims_go_to_the_higher_soft_score_and_masks_are_disjoint() -> None:
    depth = np.full((H, W), 0.8)
    m1 = np.zeros((H, W), bool)
    m2 = np.zeros((H, W), bool)
    m1[20:70, 20:90] = True
    m2[40:100, 60:140] = True
    p1 = np.where(m1, 0.9, 0.0).astype(np.float32)
    p2 = np.where(m2, 0.7, 0.0).astype(np.float32)
    opts = MaskRefineOptions(max_hole_px=0, min_kept_fraction=0.0)
    out = refine_masks([soft_of(p1), soft_of(p2)], depth, (H, W), opts)
    assert not (out[0] & out[1]).any()
    assert (out[0] == m1).all()
    assert (out[1] == (m2 & ~m1)).all()


def test_a_duplicate_that_keeps_little_of_its_mask_is_emptied() -> None:
    depth = np.full((H, W), 0.8)
    big = np.zeros((H, W), bool)
    big[20:100, 20:120] = True
    dup = np.zeros((H, W), bool)
    dup[25:100, 25:125] = True  # mostly inside `big`: a second, weaker detection of the same part
    p1 = np.where(big, 0.95, 0.0).astype(np.float32)
    p2 = np.where(dup, 0.8, 0.0).astype(np.float32)
    out = refine_masks([soft_of(p1), soft_of(p2)], depth, (H, W), MaskRefineOptions(min_kept_fraction=0.5))
    assert (out[0] == big).all()
    assert not out[1].any()
    kept = refine_masks([soft_of(p1), soft_of(p2)], depth, (H, W), MaskRefineOptions(min_kept_fraction=0.0))
    assert (kept[1] == (dup & ~big)).all()


def test_small_holes_are_filled_large_ones_kept() -> None:
    mask = np.zeros((H, W), bool)
    mask[20:100, 20:140] = True
    prob = np.where(mask, 0.95, 0.0).astype(np.float32)
    prob[50:55, 50:55] = 0.1  # small hole (25 px)
    prob[30:90, 90:130] = 0.0  # large hole (2400 px)
    out = refine_masks([soft_of(prob)], None, (H, W), MaskRefineOptions(max_hole_px=100))[0]
    assert out[50:55, 50:55].all()
    assert not out[30:90, 90:130].any()


def test_without_depth_or_rgb_it_is_the_plain_threshold() -> None:
    _, a, _ = two_blocks()
    p = blurred(a, 3.0)
    out = refine_masks([soft_of(p)], None, (H, W))[0]
    assert (out == (p > 0.5)).all()
    invalid = np.zeros((H, W))  # a depth image without valid pixels acts the same
    out2 = refine_masks([soft_of(p)], invalid, (H, W))[0]
    assert (out2 == out).all()


def test_colour_decides_where_depth_has_holes_along_the_border() -> None:
    depth, a, b = two_blocks()
    ring = cv2.dilate(a.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & ~cv2.erode(
        a.astype(np.uint8), np.ones((7, 7), np.uint8)
    ).astype(bool)
    depth[ring] = 0.0  # the sensor drops pixels along depth steps
    rgb = np.full((H, W, 3), 90, np.uint8)
    rgb[a] = (220, 40, 30)
    rgb[b] = (30, 200, 60)
    pa = blurred(a, 4.0, (3, 3))
    with_colour = refine_masks([soft_of(pa)], depth, (H, W), rgb=rgb)[0]
    without = refine_masks([soft_of(pa)], depth, (H, W), MaskRefineOptions(colour_px=0), rgb=rgb)[0]
    assert iou(with_colour, a) > 0.97
    assert iou(with_colour, a) > iou(without, a) + 0.02


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 140), st.integers(0, 100), st.integers(3, 60), st.integers(3, 60)),
        min_size=1,
        max_size=6,
    ),
    st.integers(0, 2**16),
)
def test_masks_stay_in_their_windows_and_never_overlap(rects: list[tuple[int, int, int, int]], seed: int) -> None:
    rng = np.random.default_rng(seed)
    depth = 0.8 - 0.03 * rng.random((H, W))
    depth[rng.random((H, W)) < 0.05] = 0.0
    rgb = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
    soft = []
    for x, y, w, h in rects:
        prob = rng.random((h, w)).astype(np.float32)
        soft.append(SoftMask(prob, x - 5, y - 5))  # windows may stick out of the frame
    out = refine_masks(soft, depth, (H, W), rgb=rgb)
    assert out.shape == (len(rects), H, W)
    assert out.sum(0).max() <= 1
    for k, (x, y, w, h) in enumerate(rects):
        inside = np.zeros((H, W), bool)
        inside[max(y - 5, 0) : max(y - 5 + h, 0), max(x - 5, 0) : max(x - 5 + w, 0)] = True
        assert not (out[k] & ~inside).any()


def test_bad_inputs() -> None:
    with pytest.raises(InputError):
        MaskRefineOptions(grow_prob=0.0)
    with pytest.raises(InputError):
        MaskRefineOptions(median_px=4)
    with pytest.raises(InputError):
        MaskRefineOptions(min_kept_fraction=1.5)
    with pytest.raises(InputError):
        MaskRefineOptions(edge_step_m=-1.0)
    soft = [SoftMask(np.ones((4, 4), np.float32), 0, 0)]
    with pytest.raises(InputError):
        refine_masks(soft, np.zeros((5, 5)), (H, W))
    with pytest.raises(InputError):
        refine_masks(soft, None, (H, W), rgb=np.zeros((H, W), np.uint8))
    with pytest.raises(InputError):
        refine_masks([SoftMask(np.ones(4, np.float32), 0, 0)], None, (H, W))
    assert refine_masks([], None, (H, W)).shape == (0, H, W)
