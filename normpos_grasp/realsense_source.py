"""A live Intel RealSense camera as a cell-loop `FrameSource` (optional extra: `pip install 'normpos-grasp[camera]'`).

Depth is aligned to the colour stream; the frame's camera carries the colour sensor's factory intrinsics (as the
device reports them) and the cell's calibrated `world_from_camera`. Picks are not checked (no ground truth): the
arm's grip-detect input is the only evidence, read by the driver.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.errors import InputError, MissingDependency, NormposError
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.typing import FloatArray

log = logging.getLogger(__name__)


class CameraError(NormposError):
    """The camera did not deliver a frame (unplugged, busy, timed out)."""


@dataclass(frozen=True)
class RealSenseOptions:
    """Stream settings. width, height: pixels of both streams; fps: frames per second; timeout_s: longest wait for
    a frame pair, s; warmup_frames: frames dropped after start while auto-exposure settles; serial: device serial
    number ('' = the first device found)."""

    width: int = 640
    height: int = 480
    fps: int = 30
    timeout_s: float = 5.0
    warmup_frames: int = 15
    serial: str = ""


def _import_rs() -> Any:
    try:
        import pyrealsense2 as rs  # type: ignore[import-not-found, import-untyped, unused-ignore]
    except ImportError as exc:
        raise MissingDependency("pyrealsense2", "camera", "the RealSense frame source") from exc
    return rs


def camera_from_intrinsics(intr: Any, depth_scale_m: float, world_from_camera: FloatArray | None) -> Camera:
    """A `Camera` from a pyrealsense2 `intrinsics` object (fx, fy, ppx, ppy, width, height, model, coeffs).

    Coefficients are kept for the (modified) Brown-Conrady model, OpenCV's forward model; others (inverse
    Brown-Conrady, F-theta) cannot be expressed in `Camera.distortion` and are dropped with a warning.
    """
    k = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]], dtype=np.float64)
    coeffs = np.asarray(list(intr.coeffs), dtype=np.float64)
    model = str(getattr(intr, "model", "")).rsplit(".", 1)[-1]
    forward = model in ("brown_conrady", "modified_brown_conrady", "")
    if coeffs.size not in (4, 5, 8, 12) or not forward:
        if np.any(coeffs != 0.0):
            log.warning(
                "RealSense distortion model %r is not OpenCV's forward model; its coefficients are ignored "
                "(calibrate the intrinsics with `normpos-grasp calibrate` if they matter)",
                model,
            )
        coeffs = np.zeros(5)
    return Camera(k, int(intr.width), int(intr.height), coeffs, float(depth_scale_m), world_from_camera)


class RealSenseSource:
    """Frames from a RealSense device (depth aligned to colour) at the cell's `world_from_camera` (4, 4)."""

    def __init__(self, world_from_camera: FloatArray | None, options: RealSenseOptions | None = None) -> None:
        if world_from_camera is None:
            raise InputError(
                "a live camera needs the cell's camera.world_from_camera (calibrate it: `normpos-grasp calibrate`)"
            )
        self.options = options or RealSenseOptions()
        self.world_from_camera = np.asarray(world_from_camera, dtype=np.float64)
        rs = _import_rs()
        self._rs = rs
        self._pipeline = rs.pipeline()
        config = rs.config()
        if self.options.serial:
            config.enable_device(self.options.serial)
        o = self.options
        config.enable_stream(rs.stream.depth, o.width, o.height, rs.format.z16, o.fps)
        config.enable_stream(rs.stream.color, o.width, o.height, rs.format.rgb8, o.fps)
        try:
            profile = self._pipeline.start(config)
        except RuntimeError as exc:
            what = f"{o.width}x{o.height} @ {o.fps} fps"
            raise CameraError(f"cannot start the RealSense streams ({what}): {exc}") from exc
        self._depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        self._align = rs.align(rs.stream.color)
        self._index = 0
        self._camera: Camera | None = None
        for _ in range(o.warmup_frames):
            self._wait()

    @property
    def exhausted(self) -> bool:
        return False

    def _wait(self) -> Any:
        try:
            return self._pipeline.wait_for_frames(int(self.options.timeout_s * 1000))
        except RuntimeError as exc:
            raise CameraError(f"no frame from the RealSense within {self.options.timeout_s} s: {exc}") from exc

    def capture(self) -> RGBDFrame:
        frames = self._align.process(self._wait())
        depth, color = frames.get_depth_frame(), frames.get_color_frame()
        if not depth or not color:
            raise CameraError("the RealSense delivered an incomplete frame pair (depth or colour missing)")
        if self._camera is None:
            intr = color.profile.as_video_stream_profile().get_intrinsics()
            self._camera = camera_from_intrinsics(intr, self._depth_scale, self.world_from_camera)
        raw = np.asanyarray(depth.get_data())
        depth_m = raw.astype(np.float64) * self._depth_scale
        rgb = np.ascontiguousarray(np.asanyarray(color.get_data()), dtype=np.uint8)
        frame = RGBDFrame(rgb, depth_m, self._camera, time.time(), 0, self._index)
        self._index += 1
        return frame

    def check_pick(self, plan: PickPlan) -> str:
        return "not_checked"

    def close(self) -> None:
        try:
            self._pipeline.stop()
        except RuntimeError as exc:  # already stopped
            log.debug("RealSense stop: %s", exc)
