"""The demo: a synthetic bin in a packaged cell, picked part by part on the loopback UR controller.

`run_demo` synthesises a physics-settled bin, then repeats capture -> segment -> measure -> fit -> plan ->
execute (real ur_rtde client against the emulator in its own process, or the simulated driver if the emulator
cannot start) -> physics check of the pick, until the bin is empty or nothing is reachable. It writes a report
folder: overlay PNGs, a GLB digital twin, a self-contained HTML page, plan JSONs, timings and a summary.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.cell.config import CellConfig, resolve_cell
from normpos_grasp.errors import InputError, NormposError
from normpos_grasp.execution.driver import ArmDriver
from normpos_grasp.loop import PickRecord, SyntheticBinSource, run_cell_loop
from normpos_grasp.perception.factory import SegmenterChoice, choose_segmenter
from normpos_grasp.report.frame import frame_overlay, frame_twin
from normpos_grasp.report.html import report_page, table_html, write_page
from normpos_grasp.report.overlay import encode_png

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoOptions:
    """Demo settings. parts: parts dropped into the bin; max_picks: loop turns; sensor: depth-noise preset;
    segmenter: 'model' (bundled ONNX), 'depth' (model-free) or 'gt' (the synthetic truth masks); use_emulator:
    try the loopback UR controller first; emulator_host: 127.0.0.x address for it; arrive_tol_rad: a move is
    complete when every joint is this close to its goal, rad (the issue's 1e-3 rad execution tolerance);
    part_names: library parts to draw from (empty: all); library: part libraries (templates.library.resolve_library
    entries: folders or 'builtin'; empty = the built-in parts)."""

    cell: str = "ur5e_bin_parallel"
    seed: int = 0
    parts: int = 4
    max_picks: int = 8
    sensor: str = "d435"
    segmenter: str = "model"
    use_emulator: bool = True
    emulator_host: str = "127.0.0.1"
    arrive_tol_rad: float = 1e-3
    part_names: tuple[str, ...] = ()
    library: tuple[str, ...] = ()


@dataclass(frozen=True, eq=False)
class DemoResult:
    """What the demo did: the loop's records, the driver that ran ('emulator' or 'simulated'), the report files."""

    records: list[PickRecord]
    driver: str
    driver_note: str
    segmenter: str
    files: dict[str, Path]
    summary: dict[str, Any]


def demo_segmenter(kind: str, source: SyntheticBinSource | None = None) -> SegmenterChoice:
    """The requested segmenter ('model' falls back to the depth segmenter, logged, when the bundled model cannot be
    loaded); 'gt' takes the synthetic bin's true masks (needs `source`): it checks everything after segmentation."""
    truth = source.ground_truth_segmenter if source is not None else None
    return choose_segmenter("auto" if kind == "model" else kind, ground_truth=truth)


@contextlib.contextmanager
def arm_driver(cell: CellConfig, options: DemoOptions, log_path: Path) -> Iterator[tuple[ArmDriver, str, str]]:
    """The emulator with the real ur_rtde client, else the simulated driver; yields (driver, kind, note).

    Only a failure to START the emulator falls back to the simulated driver; faults while picking propagate.
    """
    from normpos_grasp.execution.driver import DriverOptions
    from normpos_grasp.execution.safety import SafetyLimits
    from normpos_grasp.execution.sim_driver import SimDriver

    limits = SafetyLimits.from_cell(cell)
    driver_options = DriverOptions(arrive_tol_rad=options.arrive_tol_rad)
    if options.use_emulator:
        with contextlib.ExitStack() as stack:
            try:
                from normpos_grasp.execution.rtde_driver import RtdeDriver
                from normpos_grasp.sim.ur_emulator.process import EmulatorProcess

                emulator = stack.enter_context(
                    EmulatorProcess(options.emulator_host, cell.robot_model, log_path=log_path, verbose=0)
                )
                rtde = RtdeDriver(emulator.host, limits, options=driver_options)
                rtde.connect()
                stack.callback(rtde.disconnect)
                # start where the cell's program starts: at home
                rtde.move_joints(np.asarray(cell.home_q)[None], 1.0, 2.0)
            except (NormposError, OSError) as exc:
                note = f"the loopback UR controller could not start ({exc}); using the simulated driver"
                log.warning(note)
            else:
                yield rtde, "emulator", f"loopback UR controller at {emulator.host} (real ur_rtde client)"
                return
    else:
        note = "simulated driver (emulator disabled)"
    sim = SimDriver(limits, q_home=np.asarray(cell.home_q, dtype=np.float64), options=driver_options)
    sim.connect()
    try:
        yield sim, "simulated", note
    finally:
        sim.disconnect()
        sim.shutdown()


def run_demo(
    out_dir: str | Path,
    options: DemoOptions | None = None,
    on_step: Callable[[str], None] | None = None,
    on_pick: Callable[[PickRecord], None] | None = None,
) -> DemoResult:
    """Run the demo and write its report into `out_dir` (created). `on_step` hears stage names for progress."""
    opts = options or DemoOptions()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    step = on_step or (lambda _msg: None)
    t_start = time.perf_counter()
    step("loading the cell")
    cell = resolve_cell(opts.cell)
    step(f"dropping {opts.parts} parts into the bin (physics)")
    from normpos_grasp.templates.library import resolve_library

    library = list(resolve_library(opts.library))
    source = SyntheticBinSource(cell, opts.parts, opts.seed, opts.sensor, library, parts=opts.part_names)
    choice = demo_segmenter(opts.segmenter, source)
    segmenter, seg_kind = choice.segmenter, choice.kind
    step("starting the loopback UR controller")
    with arm_driver(cell, opts, out / "emulator.log") as (driver, driver_kind, note):
        step(f"picking with the {driver_kind} driver")
        records = run_cell_loop(
            cell, source, segmenter, library, driver, execute=True, max_picks=opts.max_picks, on_pick=on_pick
        )
    step("writing the report")
    files = write_report(out, records, cell, seg_kind, f"{driver_kind}: {note}")
    summary = summarise(records, time.perf_counter() - t_start, driver_kind, seg_kind, source.layout.n_parts)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    files["summary"] = out / "summary.json"
    return DemoResult(records, driver_kind, note, seg_kind, files, summary)


def pick_row(record: PickRecord) -> dict[str, Any]:
    """One line of the summary table."""
    result = record.result
    plan = record.plan_json or {}
    grasp = plan.get("grasp") or {}
    target = plan.get("target") or {}
    path = 0.0
    waypoints = plan.get("joint_waypoints") or []
    if len(waypoints) > 1:
        q = np.array([w["q"] for w in waypoints])
        path = float(np.abs(np.diff(q, axis=0)).sum())
    return {
        "pick": record.index + 1,
        "objects": len(result.instances),
        "fits accepted": f"{len(result.accepted_fits)}/{len(result.fits)}",
        "target": target.get("template", "-"),
        "grasp": f"{grasp.get('scheme', '-')} {grasp.get('id', '')}".strip(),
        "joint path (rad)": round(path, 2),
        "outcome": f"{record.status} ({record.check})",
        "fault": record.fault or "-",
        **{f"{k} ms": round(v, 1) for k, v in record.timings_ms.items()},
    }


def summarise(records: list[PickRecord], wall_s: float, driver: str, segmenter: str, left: int) -> dict[str, Any]:
    picked = sum(1 for r in records if r.status == "picked")
    return {
        "picks_attempted": sum(1 for r in records if r.status in ("picked", "pick_failed")),
        "picks_succeeded": picked,
        "parts_left_in_bin": left,
        "stopped_because": records[-1].status if records else "no frames",
        "driver": driver,
        "segmenter": segmenter,
        "wall_time_s": round(wall_s, 2),
        "picks": [pick_row(r) for r in records],
    }


def write_report(
    out: Path, records: list[PickRecord], cell: CellConfig, segmenter: str, driver: str
) -> dict[str, Path]:
    """Overlay PNG and plan JSON per pick, a GLB twin and the HTML page of the first pick, timings."""
    files: dict[str, Path] = {}
    images: dict[str, bytes] = {}
    for record in records:
        png = encode_png(frame_overlay(record.result))
        path = out / f"overlay_{record.index + 1:02d}.png"
        path.write_bytes(png)
        files[path.stem] = path
        images[f"Pick {record.index + 1}: masks, fitted templates and the chosen grasp"] = png
        if record.plan_json is not None:
            plan_path = out / f"plan_{record.index + 1:02d}.json"
            plan_path.write_text(json.dumps(record.plan_json, indent=1))
            files[plan_path.stem] = plan_path
    if not records:
        raise InputError("the demo produced no frames; nothing to report")
    twin = frame_twin(records[0].result, cell, candidates=True)
    twin.export_glb(out / "scene.glb")
    files["scene"] = out / "scene.glb"
    timings = [{"pick": r.index + 1, **{k: round(v, 2) for k, v in r.timings_ms.items()}} for r in records]
    (out / "timings.json").write_text(json.dumps(timings, indent=1))
    files["timings"] = out / "timings.json"
    sections = {
        "Summary": f"<p>cell <b>{cell.name}</b>, robot {cell.robot_model}, tool {cell.tool.name}; segmenter "
        f"{segmenter}; driver {driver}</p>" + table_html([pick_row(r) for r in records]),
    }
    write_page(out / "report.html", report_page("normpos-grasp demo", twin, images, sections))
    files["report"] = out / "report.html"
    return files
