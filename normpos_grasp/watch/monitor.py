"""The zone watch thread: reads a depth stream, runs the detector on every frame, stops the arm on an intrusion.

The stop goes through the driver's `request_stop` (thread-safe): the motion call in progress sends stopJ (or a
protective stop where the cell asks for one) at its next state poll and raises `ZoneIntrusion`. A stream that
delivers no frame for `max_gap_s` while armed is a blind watch and stops the arm too.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.typing import FloatArray
from normpos_grasp.watch.expected import joint_path
from normpos_grasp.watch.intrusion import FrameCheck, IntrusionDetector

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class StreamFrame:
    """One depth frame of the stream: depth_m (H, W) metres (0 = none); stamp: time.monotonic() when it arrived,
    s; q: (6,) commanded joints at its exposure, rad (None: ask the watch's `q_source`)."""

    depth_m: FloatArray
    stamp: float
    q: FloatArray | None = None
    index: int = -1


class DepthStream(Protocol):
    """A camera's depth stream while the arm moves."""

    def read(self, timeout_s: float) -> StreamFrame | None:
        """The next frame, waiting at most `timeout_s` s; None when none came."""
        ...


class Stopper(Protocol):
    def request_stop(self, reason: str, protective: bool = False, detail: Any = None) -> None: ...


@dataclass(frozen=True)
class StopEvent:
    """A stop the watch asked for: frame_stamp (arrival of the frame that showed it), requested_at, both
    time.monotonic() s; reason; intrusions as dicts; frame index; points: world samples (N, 3) of each intrusion."""

    frame_stamp: float
    requested_at: float
    reason: str
    intrusions: tuple[dict[str, Any], ...] = ()
    frame_index: int = -1
    points: tuple[FloatArray, ...] = field(default=(), repr=False)

    def to_dict(self) -> dict[str, Any]:
        return {
            "frame": self.frame_index,
            "reason": self.reason,
            "decision_ms": round((self.requested_at - self.frame_stamp) * 1e3, 2),
            "intrusions": list(self.intrusions),
        }


@dataclass
class WatchLog:
    """What the watch saw: frames checked, the slowest check (ms), the stop events, the last check."""

    frames: int = 0
    worst_ms: float = 0.0
    events: list[StopEvent] = field(default_factory=list)
    last: FrameCheck | None = None


class ZoneWatch:
    """Runs `detector` on `stream` in a daemon thread while started; on an intrusion calls
    `stopper.request_stop(reason, protective, detail)` once (until `rearm()`).

    q_source: the commanded joints now (read once per frame; a frame's own joints are used when it carries them);
    latency_s: the arm's silhouette covers every pose read during this window before the check; held_radius_m:
    radius of the held part around the TCP (set by the loop); on_check / on_event: callbacks (live view) from the
    watch thread; switch_interval_s: while started, the interpreter's thread switch interval is lowered to this
    (process-wide, restored by `stop`; None: left alone). The check makes a few hundred numpy calls, each of which
    may hand the GIL to the stream's and the driver's threads, and each hand-back waits up to one interval (5 ms by
    default): on the loopback controller a 25 ms check took 120-360 ms of wall clock at 5 ms, 50-100 ms at 0.5 ms.
    """

    def __init__(
        self,
        detector: IntrusionDetector,
        stream: DepthStream,
        stopper: Stopper,
        *,
        protective: bool = False,
        q_source: Callable[[], FloatArray] | None = None,
        max_gap_s: float = 0.5,
        latency_s: float = 0.1,
        on_check: Callable[[StreamFrame, FrameCheck], None] | None = None,
        on_event: Callable[[StopEvent], None] | None = None,
        switch_interval_s: float | None = 0.0005,
    ) -> None:
        self.detector = detector
        self.switch_interval_s = switch_interval_s
        self._saved_interval: float | None = None
        self.stream = stream
        self.stopper = stopper
        self.protective = protective
        self.q_source = q_source
        self.max_gap_s = max_gap_s
        self.latency_s = latency_s
        self._history: deque[tuple[float, FloatArray]] = deque(maxlen=256)
        self.on_check = on_check
        self.on_event = on_event
        self.held_radius_m = 0.0
        self.log = WatchLog()
        self._tripped = threading.Event()
        self._halt = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    @property
    def tripped(self) -> bool:
        return self._tripped.is_set()

    def start(self) -> ZoneWatch:
        self._halt.clear()
        if self.switch_interval_s is not None and self._saved_interval is None:
            self._saved_interval = sys.getswitchinterval()
            sys.setswitchinterval(min(self._saved_interval, self.switch_interval_s))
        self._thread = threading.Thread(target=self._run, name="normpos-zone-watch", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._halt.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._saved_interval is not None:
            sys.setswitchinterval(self._saved_interval)
            self._saved_interval = None

    def rearm(self) -> None:
        self._tripped.clear()

    def __enter__(self) -> ZoneWatch:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _trip(self, reason: str, frame: StreamFrame | None, check: FrameCheck | None) -> None:
        if self._tripped.is_set():
            return
        self._tripped.set()
        now = time.monotonic()
        intr = tuple(i.to_dict() for i in check.intrusions) if check is not None else ()
        stamp = frame.stamp if frame is not None else now
        pts = tuple(i.points for i in check.intrusions) if check is not None else ()
        event = StopEvent(stamp, now, reason, intr, frame.index if frame is not None else -1, pts)
        detail = {"frame_stamp": stamp, "requested_at": now, **event.to_dict()}
        self.stopper.request_stop(reason, self.protective, detail)
        self.log.events.append(event)
        log.warning("zone watch: %s", reason)
        if self.on_event is not None:
            self.on_event(event)

    def check_frame(self, frame: StreamFrame) -> FrameCheck:
        """Check one frame now (also what the thread does); trips the stop on an intrusion."""
        now = time.monotonic()
        if frame.q is not None:
            self._history.append((frame.stamp, np.asarray(frame.q, dtype=np.float64)))
        elif self.q_source is not None:
            self._history.append((now, np.asarray(self.q_source(), dtype=np.float64)))
        else:
            raise InputError("a stream frame without joints needs the watch's q_source")
        path = joint_path(list(self._history), min(now, frame.stamp) - self.latency_s)
        check = self.detector.check(frame.depth_m, path, self.held_radius_m)
        self.log.frames += 1
        self.log.worst_ms = max(self.log.worst_ms, check.elapsed_ms)
        self.log.last = check
        if not check.clear:
            first = check.intrusions[0]
            where = (
                f"coming into zone {first.zone!r} ({first.distance_m * 100:.0f} cm away, {first.n_px} px"
                if first.approaching
                else f"in zone {first.zone!r} ({first.n_in_zone} px"
            )
            self._trip(f"{first.label} {where}, at {', '.join(f'{v:.2f}' for v in first.centroid)} m)", frame, check)
        if self.on_check is not None:
            self.on_check(frame, check)
        return check

    def _run(self) -> None:
        last = time.monotonic()
        try:
            while not self._halt.is_set():
                frame = self.stream.read(0.05)
                now = time.monotonic()
                if frame is None:
                    if now - last > self.max_gap_s:
                        self._trip(f"watch stream stalled: no depth frame for {now - last:.2f} s", None, None)
                        last = now
                    continue
                last = now
                self.check_frame(frame)
        except BaseException as exc:  # a failing watch must stop the arm, never vanish silently
            self._error = exc
            log.exception("zone watch failed")
            self._trip(f"zone watch failed: {type(exc).__name__}: {exc}", None, None)
