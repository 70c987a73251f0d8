"""The watch of one cell loop: the drift check before each plan, the zone watch during each execution, and the
resume rules after a zone stop.

After a zone stop the loop never resumes the old plan: `after_stop` waits (acknowledgement first, where the cell
asks for one) until the stream shows the zones clear for `clear_frames` frames in a row against the same expected
scene, clears the driver's latch (`resume()`), and the loop then re-captures, re-measures and re-plans from where
the arm stopped. A protective stop must be unlocked on the pendant before `resume()` succeeds.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell.config import CellConfig, WatchSpec
from normpos_grasp.errors import DriverFault, InputError, ZoneIntrusion
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.typing import FloatArray
from normpos_grasp.watch.drift import FrameDriftCheck
from normpos_grasp.watch.expected import ExpectedScene, SigmaFn
from normpos_grasp.watch.intrusion import FrameCheck, IntrusionDetector
from normpos_grasp.watch.monitor import DepthStream, StopEvent, StreamFrame, ZoneWatch

log = logging.getLogger(__name__)

StreamFactory = Callable[[RGBDFrame, Any], DepthStream]  # (reference frame, driver) -> an open depth stream
Acknowledge = Callable[[str], bool]  # the stop's one-line description -> True to re-plan, False to end the loop


class CellWatch:
    """Watch settings and state for `run_cell_loop(watch=...)`.

    spec: the cell's `watch:` section; sigma: one frame's depth noise RMS at depth z (m -> m), at the stream's
    native resolution; stream: opens the depth stream for one execution (None: no zone watch, drift check only);
    acknowledge: asked after every zone stop when `spec.require_ack` (a CLI prompt, a live-view button, a PLC
    input); drift: the per-frame static-reference check (None: none); on_event / on_check: live-view callbacks;
    clear_frames / clear_timeout_s: how many clear frames in a row a resume needs, and how long to wait for them;
    max_gap_s: a stream silent this long while the arm moves stops it (a blind watch), s.
    """

    def __init__(
        self,
        cell: CellConfig,
        spec: WatchSpec,
        sigma: SigmaFn,
        *,
        stream: StreamFactory | None = None,
        acknowledge: Acknowledge | None = None,
        drift: FrameDriftCheck | None = None,
        on_event: Callable[[StopEvent], None] | None = None,
        on_check: Callable[[StreamFrame, FrameCheck], None] | None = None,
        clear_frames: int = 10,
        clear_timeout_s: float = 60.0,
        max_gap_s: float = 0.5,
    ) -> None:
        if spec.require_ack and acknowledge is None:
            raise InputError("the cell's watch.require_ack needs an acknowledgement (a prompt, button or input)")
        self.cell, self.spec, self.sigma = cell, spec, sigma
        self.stream_factory = stream
        self.acknowledge = acknowledge
        self.drift = drift
        self.on_event, self.on_check = on_event, on_check
        self.clear_frames, self.clear_timeout_s = clear_frames, clear_timeout_s
        self.max_gap_s = max_gap_s
        self.arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
        self.events: list[StopEvent] = []
        self._last: tuple[ZoneWatch, DepthStream] | None = None

    @property
    def watches_zones(self) -> bool:
        return bool(self.spec.zones) or self.spec.arm_margin_m > 0

    def check_drift(self, frame: RGBDFrame) -> None:
        """Raise CameraMoved (saying by how much) when the frame shows the camera moved; nothing without a check."""
        if self.drift is not None:
            self.drift.check(frame)

    def held_radius(self, plan: PickPlan) -> float:
        """Radius around the TCP the held part may occupy (its farthest vertex from the grasp TCP + 2 cm swing), m;
        the cell's `held_radius_m` when given."""
        if self.spec.held_radius_m > 0:
            return self.spec.held_radius_m
        if plan.chosen is None:
            return 0.0
        target = plan.targets[plan.chosen.candidate.target]
        verts = np.asarray(getattr(target.mesh, "vertices", np.zeros((1, 3))), dtype=np.float64)
        world = verts @ target.world_from_object[:3, :3].T + target.world_from_object[:3, 3]
        tcp = np.asarray(plan.chosen.candidate.world_from_tcp)[:3, 3]
        return float(np.linalg.norm(world - tcp, axis=1).max()) + 0.02

    def expected(self, frame: RGBDFrame, q_capture: FloatArray | None) -> ExpectedScene:
        s = self.spec
        return ExpectedScene(
            frame.camera,
            frame.depth_m,
            self.sigma,
            self.arm,
            self.cell.tool,
            downsample=s.downsample,
            k_sigma=s.k_sigma,
            pad_m=s.silhouette_pad_m,
            q_capture=q_capture,
            static_boxes=self.cell.static_boxes,
            floor_z=self.cell.floor_z,
        )

    @contextmanager
    def watching(
        self, frame: RGBDFrame, driver: Any, q_capture: FloatArray | None, held_radius_m: float = 0.0
    ) -> Iterator[ZoneWatch | None]:
        """Watch the zones while the body runs (the plan's execution); the stream opens before and closes after."""
        if not self.watches_zones or self.stream_factory is None:
            yield None
            return
        detector = IntrusionDetector.from_spec(self.expected(frame, q_capture), self.spec)
        stream = self.stream_factory(frame, driver)

        def heard(event: StopEvent) -> None:
            self.events.append(event)
            if self.on_event is not None:
                self.on_event(event)

        zw = ZoneWatch(
            detector,
            stream,
            driver,
            protective=self.spec.stop == "protective",
            q_source=lambda: driver.state().q,
            latency_s=self.spec.latency_s,
            max_gap_s=self.max_gap_s,
            on_check=self.on_check,
            on_event=heard,
        )
        zw.held_radius_m = held_radius_m
        zw.start()
        try:
            yield zw
        finally:
            zw.stop()
            self._last = (zw, stream)
            close = getattr(stream, "close", None)
            if callable(close) and not zw.tripped:
                close()

    def after_stop(self, driver: Any, exc: ZoneIntrusion) -> bool:
        """The resume rules after a zone stop; True when the loop may re-capture and re-plan, False to end it."""
        message = str(exc)
        if self.spec.require_ack:
            assert self.acknowledge is not None
            if not self.acknowledge(f"zone stop: {message}. Clear the cell, then acknowledge to re-plan"):
                log.warning("zone stop not acknowledged: loop ends")
                self._close_last()
                return False
        clear = self._wait_clear(driver)
        self._close_last()
        if not clear:
            log.error("zones not clear within %.0f s after the zone stop: loop ends", self.clear_timeout_s)
            return False
        try:
            driver.resume()
        except DriverFault as err:
            log.error("cannot resume after the zone stop: %s", err)
            return False
        return True

    def _wait_clear(self, driver: Any) -> bool:
        if self._last is None:
            return True
        zw, stream = self._last
        detector = zw.detector
        q = driver.state().q
        deadline = time.monotonic() + self.clear_timeout_s
        run = 0
        while time.monotonic() < deadline:
            frame = stream.read(0.2)
            if frame is None:
                continue
            check = detector.check(frame.depth_m, q, zw.held_radius_m)
            if self.on_check is not None:
                self.on_check(frame, check)
            run = run + 1 if check.clear else 0
            if run >= self.clear_frames:
                return True
        return False

    def _close_last(self) -> None:
        if self._last is not None:
            close = getattr(self._last[1], "close", None)
            if callable(close):
                close()
            self._last = None


def synthetic_stream_factory(
    cell: CellConfig, sensor: Any, truth_depth: Callable[[], FloatArray], fps: float = 30.0, seed: int = 0
) -> StreamFactory:
    """A factory of 30 fps synthetic streams (watch.synthetic) for a simulated cell: the true depth of the scene
    the loop captured last (`truth_depth()`, the bin without the arm), the arm at the driver's measured joints."""
    from normpos_grasp.watch.synthetic import SyntheticCellStream, ThreadedStream

    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    counter = [seed]

    def open_stream(frame: RGBDFrame, driver: Any) -> DepthStream:
        counter[0] += 1
        scene = SyntheticCellStream(frame.camera, truth_depth(), arm, cell.tool, sensor, counter[0], fast=True)
        return ThreadedStream(scene, lambda: driver.state().q, None, fps).start()

    return open_stream
