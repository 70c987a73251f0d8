"""The cell's `watch:` section for `normpos-grasp run`: the drift check, the zone watch's depth stream, the
operator's acknowledgement prompt (docs/watch.md)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError

# D435 colour intrinsics at 640x480 (normpos_grasp.sim.cameras), for sources whose camera is known only per frame
_DEFAULT_FX = 615.0


def prompt_ack(message: str) -> bool:
    """Ask on the terminal: Enter re-plans, 'q' (or the end of input) ends the loop."""
    print(f"{message}\n  press Enter to re-plan, or type q and Enter to stop: ", end="", file=sys.stderr, flush=True)
    line = sys.stdin.readline()
    return bool(line) and line.strip().lower() not in ("q", "quit", "stop", "n", "no")


def make_cell_watch(
    args: Any, cell: Any, source: Any, source_kind: str, on_event: Callable[[Any], None] | None = None
) -> Any:
    """The loop's CellWatch for the cell's `watch:` section (None without one). With zones and --execute the source
    must stream depth during motion: the synthetic bin does (a 30 fps synthetic stream); other sources are refused
    with one line rather than watched blind."""
    spec = cell.watch
    if spec is None:
        return None
    from normpos_grasp.sim.sensor import sensor_preset
    from normpos_grasp.watch.drift import DriftLimits, FrameDriftCheck
    from normpos_grasp.watch.session import CellWatch, synthetic_stream_factory

    sensor = sensor_preset(args.sensor if source_kind == "synthetic" else "d435")
    camera = getattr(source, "camera", None)
    fx = float(camera.fx) if camera is not None else _DEFAULT_FX

    def sigma(z: Any) -> Any:
        return np.asarray(sensor.depth_rms_m(z, fx))

    stream = None
    watches_zones = bool(spec.zones) or spec.arm_margin_m > 0
    if args.execute and watches_zones:
        if source_kind != "synthetic":
            raise InputError(
                f"the cell's watch: section asks for a zone watch, but the {source_kind} source streams no depth while "
                "the arm moves; use --source synthetic, or remove watch.zones and watch.arm_margin_m (the drift "
                "check still runs every frame)"
            )
        stream = synthetic_stream_factory(cell, sensor, lambda: source.last.rendering.depth_m, seed=int(args.seed))
    drift = None
    if spec.static_reference is not None:
        from normpos_grasp.camera.static_reference import StaticReference

        drift = FrameDriftCheck(StaticReference.load_json(spec.static_reference), None, DriftLimits.from_spec(spec))
    return CellWatch(
        cell,
        spec,
        sigma,
        stream=stream,
        acknowledge=prompt_ack if spec.require_ack else None,
        drift=drift,
        on_event=on_event,
        max_gap_s=2.0 if source_kind == "synthetic" else 0.5,  # the synthetic stream shares this machine's cores
    )
