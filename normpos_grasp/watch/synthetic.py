"""A cheap synthetic depth stream of a cell: a static background, the arm's capsules at its actual joints,
intruding boxes and capsules, and a sensor noise model (normpos_grasp.sim.sensor).

Shapes are drawn analytically (ray-box slabs, spheres strung along each capsule's axis), so a 320x240 frame costs
a few milliseconds: enough for 30 fps streams in tests, benchmarks and the simulated cell. The arm is drawn from the
same link capsules the watch predicts it with, so the stream tests the watch's latency, noise and tracking margins,
not the capsule model's fit to a real arm.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.records.tool import ToolModel
from normpos_grasp.typing import FloatArray
from normpos_grasp.watch.expected import _rays, arm_segments, render_boxes
from normpos_grasp.watch.monitor import StreamFrame
from normpos_grasp.watch.zones import ArmSegments


@dataclass(frozen=True, eq=False)
class Intruder:
    """Boxes (world_from_box (4, 4), size (3,)) and capsules (start (3,), end (3,), radius) of one intruder, m."""

    boxes: tuple[tuple[FloatArray, FloatArray], ...] = ()
    capsules: tuple[tuple[FloatArray, FloatArray, float], ...] = ()

    def moved(self, offset: FloatArray) -> Intruder:
        off = np.asarray(offset, dtype=np.float64)
        boxes = []
        for pose, size in self.boxes:
            p = np.array(pose, dtype=np.float64)
            p[:3, 3] += off
            boxes.append((p, size))
        caps = tuple((a + off, b + off, r) for a, b, r in self.capsules)
        return Intruder(tuple(boxes), caps)

    def sample_points(self, n: int = 7) -> FloatArray:
        """(M, 3) points filling the intruder (a grid in each box, points along each capsule axis), m."""
        out = []
        g = np.linspace(-0.5, 0.5, n)
        grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        for pose, size in self.boxes:
            out.append((grid * np.asarray(size)) @ np.asarray(pose)[:3, :3].T + np.asarray(pose)[:3, 3])
        for a, b, _ in self.capsules:
            out.append(a[None] + np.linspace(0, 1, n)[:, None] * (b - a)[None])
        return np.vstack(out) if out else np.zeros((0, 3))


def hand_box(centre: FloatArray, size: tuple[float, float, float] = (0.09, 0.2, 0.06)) -> Intruder:
    """A hand-sized box (default 9 x 20 x 6 cm: a flat hand with its wrist) centred at `centre`."""
    pose = np.eye(4)
    pose[:3, 3] = centre
    return Intruder(((pose, np.asarray(size, dtype=np.float64)),))


def person_shape(centre: FloatArray, reach_dir: FloatArray) -> Intruder:
    """A person leaning over the cell, seen from above: shoulders (a 45 x 25 x 30 cm box) and head (a 10 cm
    capsule) at `centre`, one arm (a 5 cm capsule, 60 cm) reaching along `reach_dir` (horizontal unit vector)."""
    c = np.asarray(centre, dtype=np.float64)
    d = np.asarray(reach_dir, dtype=np.float64)
    d = d / np.linalg.norm(d)
    side = np.array([-d[1], d[0], 0.0])
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = side, d, (0.0, 0.0, 1.0)
    pose[:3, 3] = c
    head = (c + np.array([0.0, 0.0, 0.12]) - 0.02 * d, c + np.array([0.0, 0.0, 0.2]) - 0.02 * d, 0.1)
    shoulder = c + 0.18 * side + 0.05 * d
    arm = (shoulder, shoulder + 0.6 * d - np.array([0.0, 0.0, 0.15]), 0.05)
    return Intruder(((pose, np.array([0.45, 0.25, 0.3])),), (head, arm))


def render_spheres(camera: Camera, depth: np.ndarray, segments: ArmSegments) -> None:
    """Draw capsules into `depth` (H, W) float32 in place (z-buffer min), as spheres strung along each axis."""
    rays = _rays(camera)
    cfw = camera.camera_from_world
    h, w = depth.shape
    for a, b, r in zip(segments.start, segments.end, segments.radius, strict=True):
        length = float(np.linalg.norm(b - a))
        n = max(1, int(np.ceil(length / max(0.5 * r, 0.002)))) + 1
        centres = a[None] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None]
        cam = centres @ cfw[:3, :3].T + cfw[:3, 3]
        for c in cam:
            if c[2] - r < 0.05:
                continue
            u0, v0 = camera.fx * c[0] / c[2] + camera.cx, camera.fy * c[1] / c[2] + camera.cy
            rad = camera.fx * r / (c[2] - r) + 1
            x0, x1 = max(int(u0 - rad), 0), min(int(u0 + rad) + 1, w)
            y0, y1 = max(int(v0 - rad), 0), min(int(v0 + rad) + 1, h)
            if x0 >= x1 or y0 >= y1:
                continue
            xy = rays[y0:y1, x0:x1]
            # ray p = t (x, y, 1): |t d - c|^2 = r^2; the smaller root is the front surface (t is the z-depth)
            dd = xy[..., 0] ** 2 + xy[..., 1] ** 2 + 1.0
            dc = xy[..., 0] * c[0] + xy[..., 1] * c[1] + c[2]
            disc = dc * dc - dd * (c @ c - r * r)
            ok = disc >= 0
            if not ok.any():
                continue
            t = (dc - np.sqrt(np.where(ok, disc, 0.0))) / dd
            region = depth[y0:y1, x0:x1]
            np.minimum(region, np.where(ok, t, np.inf).astype(np.float32), out=region)


class SyntheticCellStream:
    """Renders frames of a cell: `background_m` (H, W) true depth of the static scene (0 = nothing), the arm at given
    joints, intruders, and `sensor` noise (SensorModel, RGB effects off)."""

    def __init__(
        self,
        camera: Camera,
        background_m: FloatArray,
        arm: ArmModel,
        tool: ToolModel | None,
        sensor: object,
        seed: int = 0,
        held_radius_m: float = 0.0,
        fast: bool = False,
    ) -> None:
        """fast: keep the sensor's depth noise, quantisation and dropout but skip its stereo shadows, edge and
        grazing-angle holes (a 640x480 frame then costs a fraction; for live streams on small machines)."""
        self.camera = camera
        self.background = np.asarray(background_m, dtype=np.float32)
        self.arm, self.tool = arm, tool
        self.sensor = replace(
            sensor,  # type: ignore[type-var]
            rgb_read_noise_dn=0.0,
            rgb_shot_noise=0.0,
            rgb_gain=(1.0, 1.0),
            rgb_white_balance=0.0,
            rgb_gradient=0.0,
            rgb_blur_px=0.0,
        )
        if fast:
            self.sensor = replace(
                self.sensor,  # type: ignore[type-var]
                shadows=False,
                edge_hole_prob=0.0,
                grazing_deg=90.0,
                material_dropout=(),
            )
        self.rng = np.random.default_rng(seed)
        self.held_radius_m = held_radius_m
        self._rgb = np.zeros((camera.height, camera.width, 3), np.uint8)

    def truth(self, q: FloatArray | None, intruders: Sequence[Intruder] = ()) -> np.ndarray:
        """(H, W) float32 noise-free depth with the arm at `q` (None: no arm) and the intruders."""
        depth = np.where(self.background > 0, self.background, np.float32(np.inf)).astype(np.float32)
        if q is not None:
            render_spheres(self.camera, depth, arm_segments(self.arm, q, self.tool, self.held_radius_m, 0.0))
        for it in intruders:
            if it.boxes:
                boxes = render_boxes(self.camera, it.boxes)
                np.minimum(depth, np.where(boxes > 0, boxes, np.inf).astype(np.float32), out=depth)
            if it.capsules:
                caps = ArmSegments(
                    np.array([c[0] for c in it.capsules]),
                    np.array([c[1] for c in it.capsules]),
                    np.array([c[2] for c in it.capsules]),
                )
                render_spheres(self.camera, depth, caps)
        return np.where(np.isfinite(depth), depth, np.float32(0.0))

    def noisy(self, truth: np.ndarray) -> FloatArray:
        """The sensor's measurement of a true depth image."""
        from normpos_grasp.sim.render import Rendering

        h, w = truth.shape
        empty = np.zeros((0, h, w), dtype=bool)
        rendering = Rendering(self._rgb, truth.astype(np.float64), np.zeros((h, w), np.int32), empty, empty, "watch")
        _, depth = self.sensor.apply(rendering, self.camera, self.rng)  # type: ignore[attr-defined]
        return np.asarray(depth)

    def frame(self, q: FloatArray | None, intruders: Sequence[Intruder] = ()) -> FloatArray:
        return self.noisy(self.truth(q, intruders))


class ThreadedStream:
    """A live stream at `fps`: a thread renders `scene` with the arm at `q_source()` and the intruders
    `intruders(t)` (t: seconds since start) and hands out the newest frame; implements `DepthStream`."""

    def __init__(
        self,
        scene: SyntheticCellStream,
        q_source: Callable[[], FloatArray],
        intruders: Callable[[float], Sequence[Intruder]] | None = None,
        fps: float = 30.0,
    ) -> None:
        self.scene = scene
        self.q_source = q_source
        self.intruders = intruders
        self.period = 1.0 / fps
        self._queue: queue.Queue[StreamFrame] = queue.Queue(maxsize=1)
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self.t0 = 0.0
        self.first_seen: dict[int, float] = {}  # frame index -> arrival time, for frames that showed an intruder
        self.frames = 0

    def start(self) -> ThreadedStream:
        self.t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="normpos-synthetic-depth", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        k = 0
        while not self._halt.is_set():
            t_exp = time.monotonic()
            q = np.asarray(self.q_source(), dtype=np.float64)
            shown = list(self.intruders(t_exp - self.t0)) if self.intruders is not None else []
            depth = self.scene.frame(q, shown)
            stamp = time.monotonic()
            if shown:
                self.first_seen[k] = stamp
            frame = StreamFrame(depth, stamp, None, k)
            with contextlib.suppress(queue.Empty):
                self._queue.get_nowait()
            self._queue.put_nowait(frame)
            k += 1
            self.frames = k
            self._halt.wait(max(0.0, t_exp + self.period - time.monotonic()))

    def read(self, timeout_s: float) -> StreamFrame | None:
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None


def cell_background(
    cell: object, camera: Camera, n_parts: int = 6, seed: int = 0
) -> tuple[np.ndarray, list[tuple[FloatArray, FloatArray]]]:
    """True depth of a cell's static boxes (`CellConfig.static_boxes`, floor at `floor_z`) with `n_parts` random
    part-sized boxes (3-8 cm) lying in its bin; returns (depth (H, W) float32, the part boxes)."""
    rng = np.random.default_rng(seed)
    boxes = [(b.world_from_box, b.size) for b in cell.static_boxes]  # type: ignore[attr-defined]
    parts: list[tuple[FloatArray, FloatArray]] = []
    bin_spec = cell.bin  # type: ignore[attr-defined]
    if bin_spec is not None:
        lx, ly, _ = (float(v) for v in bin_spec.inner_size)
        for _ in range(n_parts):
            size = rng.uniform(0.03, 0.08, 3)
            pose = np.eye(4)
            yaw = rng.uniform(0, np.pi)
            pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
            pose[:3, 3] = [rng.uniform(-lx / 3, lx / 3), rng.uniform(-ly / 3, ly / 3), size[2] / 2]
            parts.append((bin_spec.world_from_bin @ pose, size))
    depth = render_boxes(camera, boxes + parts, getattr(cell, "floor_z", None))
    return depth, parts
