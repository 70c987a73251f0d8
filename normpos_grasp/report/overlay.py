"""Overlay picture of one frame: instance masks, labels, fitted template outlines and the chosen grasp."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.geometry.transforms import transform_points
from normpos_grasp.records.instance import Instance
from normpos_grasp.report.scene3d import palette_color
from normpos_grasp.typing import FloatArray, UInt8Array


@dataclass(frozen=True)
class OutlineItem:
    """A posed mesh to outline: `vertices` (V, 3) and `faces` (F, 3) in the world (or camera) frame."""

    vertices: FloatArray
    faces: np.ndarray
    text: str
    color: tuple[int, int, int]


def draw_overlay(
    rgb: UInt8Array,
    camera: Camera,
    instances: Sequence[Instance] = (),
    outlines: Sequence[OutlineItem] = (),
    grasp_world_from_tcp: FloatArray | None = None,
    grasp_opening_m: float = 0.0,
    alpha: float = 0.45,
) -> UInt8Array:
    """Return a new (H, W, 3) RGB picture; the input is not modified.

    Points are taken to be in the world frame when the camera has extrinsics, else in the camera frame.
    """
    out = np.array(rgb, dtype=np.float64, copy=True)
    for k, inst in enumerate(instances):
        color = np.array(palette_color(k), dtype=np.float64)
        out[inst.mask] = (1 - alpha) * out[inst.mask] + alpha * color
    picture = np.clip(out, 0, 255).astype(np.uint8)
    bgr = cv2.cvtColor(picture, cv2.COLOR_RGB2BGR)
    for k, inst in enumerate(instances):
        ys, xs = np.nonzero(inst.mask)
        if len(xs) == 0:
            continue
        text = f"{inst.label or '?'} {inst.score:.2f}"
        _label(bgr, text, (int(xs.mean()), int(ys.mean())), palette_color(k))
    for item in outlines:
        contour_mask = _silhouette(camera, item.vertices, item.faces)
        contours, _ = cv2.findContours(contour_mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(bgr, contours, -1, _bgr(item.color), 2, cv2.LINE_AA)
        if contours:
            x, y, _, _ = cv2.boundingRect(max(contours, key=cv2.contourArea))
            _label(bgr, item.text, (x, max(12, y - 4)), item.color)
    if grasp_world_from_tcp is not None:
        _draw_grasp(bgr, camera, np.asarray(grasp_world_from_tcp, dtype=np.float64), grasp_opening_m)
    return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)


def encode_png(rgb: UInt8Array) -> bytes:
    """PNG bytes of an RGB image."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - OpenCV failure
        raise RuntimeError("OpenCV could not encode the PNG")
    return bytes(buf.tobytes())


def _to_camera(camera: Camera, points: FloatArray) -> FloatArray:
    if camera.world_from_camera is None:
        return np.asarray(points, dtype=np.float64)
    return transform_points(camera.camera_from_world, points)


def _silhouette(camera: Camera, vertices: FloatArray, faces: np.ndarray) -> np.ndarray:
    pts = _to_camera(camera, vertices)
    mask = np.zeros((camera.height, camera.width), dtype=np.uint8)
    in_front = pts[:, 2] > 1e-3
    px = camera.project(np.where(in_front[:, None], pts, [0.0, 0.0, 1.0]))
    tris = np.asarray(faces)[np.all(in_front[np.asarray(faces)], axis=1)]
    polys = np.round(px[tris] * 8).astype(np.int32)  # 3 bits of sub-pixel precision
    cv2.fillPoly(mask, list(polys), 255, lineType=cv2.LINE_8, shift=3)
    return mask


def _draw_grasp(bgr: np.ndarray, camera: Camera, world_from_tcp: FloatArray, opening: float) -> None:
    half = max(opening, 0.02) / 2.0
    local = np.array(
        [[0, 0, 0], [half, 0, 0], [-half, 0, 0], [half, 0, -0.05], [-half, 0, -0.05], [0, 0, -0.12]],
        dtype=np.float64,
    )
    cam_pts = _to_camera(camera, transform_points(world_from_tcp, local))
    if np.any(cam_pts[:, 2] <= 1e-3):
        return
    p = np.round(camera.project(cam_pts)).astype(np.int32)
    color = (0, 255, 255)
    for a, b in ((1, 3), (2, 4), (3, 4), (5, 0)):
        cv2.line(bgr, tuple(int(v) for v in p[a]), tuple(int(v) for v in p[b]), color, 3, cv2.LINE_AA)
    cv2.circle(bgr, tuple(int(v) for v in p[0]), 5, (0, 0, 255), -1, cv2.LINE_AA)
    _label(bgr, "grasp", (int(p[5][0]) + 6, int(p[5][1])), (255, 255, 0))


def _label(bgr: np.ndarray, text: str, org: tuple[int, int], color: tuple[int, int, int]) -> None:
    cv2.putText(bgr, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(bgr, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.45, _bgr(color), 1, cv2.LINE_AA)


def _bgr(color: tuple[int, int, int]) -> tuple[int, int, int]:
    return (int(color[2]), int(color[1]), int(color[0]))
