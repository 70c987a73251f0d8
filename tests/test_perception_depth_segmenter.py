"""DepthSegmenter on ray-cast box scenes seen at an angle: bin walls, a bin floor above the table, L-brackets,
a square frame with the floor showing through it, dropouts on a part, and bad depth values."""

from __future__ import annotations

import numpy as np
import pytest

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.geometry.transforms import look_at
from normpos_grasp.perception.depth_segmenter import DepthSegmenter, fill_enclosed_holes
from normpos_grasp.training.metrics import mask_iou_matrix

W, H, F = 640, 480, 615.0
Box = tuple[tuple[float, float, float], tuple[float, float, float]]  # (min corner, max corner), world metres


def _camera(eye: tuple[float, float, float], target: tuple[float, float, float]) -> Camera:
    k = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1]])
    return Camera(K=k, width=W, height=H, world_from_camera=look_at(eye, target))


def _render(camera: Camera, boxes: list[Box]) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) metres along the optical axis and the index (H, W) of the box seen (-1: none) of axis-aligned
    world boxes (slab intersection; camera rays with unit z, so the ray parameter is the depth)."""
    wfc = camera.world_from_camera
    assert wfc is not None
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    d_cam = np.stack([(u - camera.K[0, 2]) / F, (v - camera.K[1, 2]) / F, np.ones_like(u)], axis=-1)
    d = d_cam @ wfc[:3, :3].T
    o = wfc[:3, 3]
    depth = np.full((H, W), np.inf)
    index = np.full((H, W), -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i, (lo, hi) in enumerate(boxes):
            t1 = (np.asarray(lo) - o) / d
            t2 = (np.asarray(hi) - o) / d
            near = np.nanmax(np.minimum(t1, t2), axis=-1)
            far = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (near <= far) & (near > 0) & (near < depth)
            depth[hit] = near[hit]
            index[hit] = i
    return np.where(np.isfinite(depth), depth, 0.0), index


def _bin(floor_top: float = 0.0, inner: float = 0.36, wall_h: float = 0.12, wall_t: float = 0.01) -> list[Box]:
    """Table slab, then a bin: floor (top at floor_top) and four walls."""
    a, b, f = inner / 2, inner / 2 + wall_t, floor_top
    return [
        ((-1.0, -1.0, -0.05), (1.0, 1.0, 0.0)),
        ((-b, -b, 0.0), (b, b, max(f, 1e-3))),
        ((a, -b, 0.0), (b, b, f + wall_h)),
        ((-b, -b, 0.0), (-a, b, f + wall_h)),
        ((-a, a, 0.0), (a, b, f + wall_h)),
        ((-a, -b, 0.0), (a, -a, f + wall_h)),
    ]


def _frame(camera: Camera, depth: np.ndarray, noise_m: float = 0.0005, seed: int = 0) -> RGBDFrame:
    rng = np.random.default_rng(seed)
    noisy = np.where(depth > 0, depth + rng.normal(0.0, noise_m, depth.shape), 0.0)
    return RGBDFrame(rgb=np.zeros((H, W, 3), np.uint8), depth_m=noisy, camera=camera)


def _ious(found: list[np.ndarray], truth: list[np.ndarray]) -> np.ndarray:
    return mask_iou_matrix(truth, found).max(axis=1) if found else np.zeros(len(truth))


def _bin_scene() -> tuple[Camera, np.ndarray, np.ndarray, int, int]:
    floor = 0.02
    parts: list[Box] = [
        ((-0.08, -0.05, floor), (-0.02, -0.01, floor + 0.03)),  # box
        ((0.03, 0.02, floor), (0.07, 0.06, floor + 0.04)),  # cube
        ((-0.05, 0.06, floor), (0.05, 0.085, floor + 0.025)),  # bar
        ((0.02, -0.10, floor), (0.10, -0.04, floor + 0.008)),  # plate
    ]
    cam = _camera((0.25, -0.35, 0.65), (0.0, 0.0, floor))
    depth, index = _render(cam, _bin(floor) + parts)
    return cam, depth, index, len(_bin(floor)), len(parts)


def test_parts_in_a_bin_seen_at_an_angle_without_the_wall_faces() -> None:
    cam, depth, index, n_bin, n_parts = _bin_scene()
    truth = [index == n_bin + k for k in range(n_parts)]
    assert all(t.sum() > 400 for t in truth)
    inst = DepthSegmenter().segment(_frame(cam, depth))
    ious = _ious([i.mask for i in inst], truth)
    assert (ious > 0.7).all(), ious
    walls = (index >= 2) & (index < n_bin)
    on_wall = [float((i.mask & walls).sum() / i.mask.sum()) for i in inst]
    # no instance on the walls' large faces; at most a thin rim fragment
    assert sum(i.mask.sum() for i, f in zip(inst, on_wall, strict=True) if f > 0.5) < 0.01 * walls.sum(), on_wall


def test_l_bracket_stays_one_part() -> None:
    """An L-bracket (a leg flat on the floor, a leg standing up: a concave inner crease with continuous depth) is one
    part, seen from its inner side and from its end. (From behind the standing leg the flat leg shows beyond an
    occluding edge, a depth jump, and the two legs are reported apart: depth alone cannot join them.)"""
    bracket: list[Box] = [
        ((-0.03, -0.03, 0.0), (0.01, 0.03, 0.008)),  # flat leg
        ((0.002, -0.03, 0.0), (0.01, 0.03, 0.04)),  # standing leg
    ]
    boxes: list[Box] = [((-1.0, -1.0, -0.05), (1.0, 1.0, 0.0)), *bracket]
    for eye in ((-0.30, -0.25, 0.60), (0.0, -0.35, 0.60)):
        cam = _camera(eye, (0.0, 0.0, 0.0))
        depth, index = _render(cam, boxes)
        inst = DepthSegmenter().segment(_frame(cam, depth))
        assert len(inst) == 1, eye
        assert _ious([inst[0].mask], [index >= 1])[0] > 0.8


def test_touching_boxes_of_other_height_split() -> None:
    """A box touching a 2 cm taller one: split at the depth jump along the taller one's top edge (camera on the tall
    side) and, camera on the low side, at the concave crease where the low top meets the tall side face (their union
    is longer than merge_max_extent_m, so the merge does not take them for one bracket-like part)."""
    pair: list[Box] = [
        ((-0.05, -0.02, 0.0), (0.0, 0.02, 0.03)),  # low box
        ((0.0, -0.03, 0.0), (0.05, 0.025, 0.05)),  # taller, wider box touching it (no face coplanar with the low one)
    ]
    boxes: list[Box] = [((-1.0, -1.0, -0.05), (1.0, 1.0, 0.0)), *pair]
    for eye in ((0.30, -0.25, 0.60), (-0.30, -0.25, 0.60)):
        cam = _camera(eye, (0.0, 0.0, 0.0))
        depth, index = _render(cam, boxes)
        inst = DepthSegmenter().segment(_frame(cam, depth))
        ious = _ious([i.mask for i in inst], [index == 1, index == 2])
        assert (ious > 0.7).all(), (eye, ious)
        assert len(inst) == 2


def test_floor_seen_through_a_frame_is_not_part_of_it() -> None:
    """A square frame (four bars) lying in a bin whose floor is 3 cm above the table: the bin floor inside the frame
    is background, the frame one part."""
    floor = 0.03
    t, a = 0.012, 0.035
    frame_bars: list[Box] = [
        ((-a, -a, floor), (a, -a + t, floor + 0.015)),
        ((-a, a - t, floor), (a, a, floor + 0.015)),
        ((-a, -a + t, floor), (-a + t, a - t, floor + 0.015)),
        ((a - t, -a + t, floor), (a, a - t, floor + 0.015)),
    ]
    boxes = _bin(floor) + frame_bars
    cam = _camera((0.05, -0.15, 0.75), (0.0, 0.0, floor))
    depth, index = _render(cam, boxes)
    n_bin = len(_bin(floor))
    truth = (index >= n_bin) & (index < n_bin + 4)
    inside = np.zeros_like(truth)
    ys, xs = np.nonzero(truth)
    inside[ys.min() : ys.max(), xs.min() : xs.max()] = True
    inside &= index == 1  # bin floor seen through the frame
    inst = DepthSegmenter().segment(_frame(cam, depth))
    assert len(inst) == 1
    assert _ious([inst[0].mask], [truth])[0] > 0.7
    assert (inst[0].mask & inside).sum() < 0.1 * inside.sum()


def test_dropouts_on_a_part_belong_to_it() -> None:
    boxes: list[Box] = [((-1.0, -1.0, -0.05), (1.0, 1.0, 0.0)), ((-0.04, -0.03, 0.0), (0.04, 0.03, 0.03))]
    cam = _camera((0.0, -0.2, 0.6), (0.0, 0.0, 0.0))
    depth, index = _render(cam, boxes)
    truth = index == 1
    holey = depth.copy()
    ys, xs = np.nonzero(truth)
    cy, cx = int(ys.mean()), int(xs.mean())
    holey[cy - 6 : cy + 6, cx - 10 : cx + 10] = 0.0  # a metal glint: no depth
    inst = DepthSegmenter().segment(_frame(cam, holey))
    assert len(inst) == 1
    assert inst[0].mask[cy - 6 : cy + 6, cx - 10 : cx + 10].mean() > 0.9


def test_fill_enclosed_holes_only_fills_holes_inside_one_label() -> None:
    lab = np.zeros((20, 30), np.int32)
    lab[2:12, 2:12] = 1
    lab[2:12, 12:22] = 2
    valid = np.ones_like(lab, bool)
    valid[5:8, 5:8] = False  # inside label 1
    valid[5:8, 10:14] = False  # between labels 1 and 2
    valid[0:2, 24:28] = False  # on the image border, background
    out = fill_enclosed_holes(lab, valid)
    assert (out[5:8, 5:8] == 1).all()
    assert (out[5:8, 10:14] == 0).all()
    assert (out[0:2, 24:28] == 0).all()
    np.testing.assert_array_equal(out[valid], lab[valid])


@pytest.mark.parametrize("value", [0.0, np.nan, np.inf, -1.0])
def test_bad_depth_values_give_no_instances(value: float) -> None:
    cam = _camera((0.0, -0.2, 0.6), (0.0, 0.0, 0.0))
    frame = RGBDFrame(rgb=np.zeros((H, W, 3), np.uint8), depth_m=np.full((H, W), value), camera=cam)
    assert DepthSegmenter().segment(frame) == []


def test_a_few_valid_pixels_give_no_instances() -> None:
    cam = _camera((0.0, -0.2, 0.6), (0.0, 0.0, 0.0))
    depth = np.zeros((H, W))
    depth[100:104, 200:204] = 0.5
    frame = RGBDFrame(rgb=np.zeros((H, W, 3), np.uint8), depth_m=depth, camera=cam)
    assert DepthSegmenter().segment(frame) == []


def test_camera_pose_is_not_needed() -> None:
    """Only intrinsics and depth are used: the same frame without world_from_camera gives the same instances."""
    boxes: list[Box] = [((-1.0, -1.0, -0.05), (1.0, 1.0, 0.0)), ((-0.04, -0.03, 0.0), (0.04, 0.03, 0.03))]
    cam = _camera((0.05, -0.2, 0.6), (0.0, 0.0, 0.0))
    depth, _ = _render(cam, boxes)
    bare = Camera(K=cam.K, width=W, height=H)
    a = DepthSegmenter().segment(_frame(cam, depth))
    b = DepthSegmenter().segment(_frame(bare, depth))
    assert len(a) == len(b) == 1
    np.testing.assert_array_equal(a[0].mask, b[0].mask)


@pytest.mark.parametrize(("h", "w"), [(1, 1), (3, 5), (8, 8), (12, 40), (61, 47)])
def test_tiny_frames_do_not_crash(h: int, w: int) -> None:
    cam = Camera(K=np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]]), width=w, height=h)
    depth = 0.6 + np.random.default_rng(0).normal(0.0, 0.001, (h, w))
    depth[h // 3 : 2 * h // 3 + 1, w // 3 : 2 * w // 3 + 1] -= 0.05
    frame = RGBDFrame(rgb=np.zeros((h, w, 3), np.uint8), depth_m=depth, camera=cam)
    inst = DepthSegmenter().segment(frame)
    assert all(i.mask.shape == (h, w) and i.label == "" for i in inst)
