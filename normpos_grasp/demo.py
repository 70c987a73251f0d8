"""The demo: a synthetic bin in a packaged cell, picked part by part on the loopback UR controller.

`run_demo` synthesises a physics-settled bin, then repeats capture -> segment -> measure -> fit -> plan ->
execute (real ur_rtde client against the emulator in its own process, or the simulated driver if the emulator
cannot start) -> physics check of the pick, until the bin is empty or nothing is reachable. It writes a report
folder: overlay PNGs, a GLB digital twin, a self-contained HTML page, plan JSONs, timings and a summary.
"""

from __future__ import annotations

import contextlib
import html
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
from normpos_grasp.perception.factory import SegmenterChoice, choose_segmenter, library_model
from normpos_grasp.planning.plan import rejections_by_target, stop_line
from normpos_grasp.report.frame import frame_overlay, frame_twin
from normpos_grasp.report.html import report_page, table_html, write_page
from normpos_grasp.report.overlay import draw_overlay, encode_png

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoOptions:
    """Demo settings. parts: parts dropped into the bin; max_picks: loop turns; sensor: depth-noise preset;
    segmenter: 'model' (bundled ONNX), 'depth' (model-free) or 'gt' (the synthetic truth masks); use_emulator:
    try the loopback UR controller first; emulator_host: 127.0.0.x address for it; arrive_tol_rad: a move is
    complete when every joint is this close to its goal, rad (the issue's 1e-3 rad execution tolerance);
    part_names: library parts to draw from (empty: all); library: part libraries (templates.library.resolve_library
    entries: folders or 'builtin'; empty = the built-in parts); max_pushes: when no grasp is feasible, push a part
    (planned on the perceived scene, `planning.push`; run on the arm and replayed in MuJoCo on the true bin) by
    `push_m` metres and look again, at most this many times; pick_unmatched: a part whose template fit was
    rejected is still picked as a box / plate from its measured oriented box (`PlanOptions.pick_unmatched`, as in
    `simulate`) instead of staying clutter."""

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
    max_pushes: int = 3
    push_m: float = 0.05
    pick_unmatched: bool = True


@dataclass(frozen=True, eq=False)
class DemoResult:
    """What the demo did: the loop's records, the driver that ran ('emulator' or 'simulated'), the report files."""

    records: list[PickRecord]
    driver: str
    driver_note: str
    segmenter: str
    files: dict[str, Path]
    summary: dict[str, Any]


def demo_segmenter(
    kind: str, source: SyntheticBinSource | None = None, model_path: str | Path | None = None
) -> SegmenterChoice:
    """The requested segmenter ('model': the model at `model_path`, default the bundled one, falling back to the
    depth segmenter, logged, when it cannot be loaded); 'gt' takes the synthetic bin's true masks (needs `source`):
    it checks everything after segmentation."""
    truth = source.ground_truth_segmenter if source is not None else None
    return choose_segmenter("auto" if kind == "model" else kind, model_path, ground_truth=truth)


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
    choice = demo_segmenter(opts.segmenter, source, library_model(opts.library))
    segmenter, seg_kind = choice.segmenter, choice.kind
    step("starting the loopback UR controller")
    with arm_driver(cell, opts, out / "emulator.log") as (driver, driver_kind, note):
        step(f"picking with the {driver_kind} driver")
        records, pushes = _pick_and_push(cell, source, segmenter, library, driver, opts, step, on_pick)
    step("writing the report")
    files = write_report(out, records, cell, seg_kind, f"{driver_kind}: {note}", source.layout.n_parts)
    summary = summarise(records, time.perf_counter() - t_start, driver_kind, seg_kind, source.layout.n_parts)
    summary["pushes"] = pushes
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    files["summary"] = out / "summary.json"
    return DemoResult(records, driver_kind, note, seg_kind, files, summary)


def _pick_and_push(
    cell: CellConfig,
    source: SyntheticBinSource,
    segmenter: Any,
    library: list[Any],
    driver: ArmDriver,
    opts: DemoOptions,
    step: Callable[[str], None],
    on_pick: Callable[[PickRecord], None] | None,
) -> tuple[list[PickRecord], list[dict[str, Any]]]:
    """The cell loop; when it stops for want of a feasible grasp, push a part (planned on what was perceived, run
    on the arm, replayed in MuJoCo on the true bin) and pick on, up to `opts.max_pushes` pushes. Returns the
    records (numbered through) and one entry per push."""
    from dataclasses import replace

    from normpos_grasp.errors import PlanningError
    from normpos_grasp.loop import _physics_gripper, tool_outputs_hook
    from normpos_grasp.pipeline import PipelineOptions
    from normpos_grasp.planning.plan import PlanOptions
    from normpos_grasp.planning.push import PushHand, plan_push, push_motion
    from normpos_grasp.sim.cell_scene import remove_parts
    from normpos_grasp.sim.physics import GripperSpec
    from normpos_grasp.sim.physics_push import simulate_push

    pipeline = PipelineOptions(plan=PlanOptions(pick_unmatched=opts.pick_unmatched))
    dual = len(cell.tools) > 1  # each plan's tool gets its outputs (the driver is in this process)
    records: list[PickRecord] = []
    pushes: list[dict[str, Any]] = []
    offset = 0

    def heard(record: PickRecord) -> None:
        if on_pick is not None:
            on_pick(replace(record, index=record.index + offset))

    while True:
        turn = run_cell_loop(
            cell, source, segmenter, library, driver, execute=True, max_picks=opts.max_picks - len(records),
            on_pick=heard, options=pipeline, before_execute=tool_outputs_hook(cell, driver) if dual else None,
        )  # fmt: skip
        records.extend(replace(r, index=r.index + offset) for r in turn)
        offset = len(records)
        if not turn or turn[-1].status != "no_feasible_grasp" or source.exhausted or cell.bin is None:
            break
        if len(pushes) >= opts.max_pushes or len(records) >= opts.max_picks:
            break
        last = turn[-1].result
        if last.plan is None or cell.tool.kind != "parallel":
            break
        spec = _physics_gripper(cell)
        if not isinstance(spec, GripperSpec):
            spec = GripperSpec.from_gripper(spec)
        hand = PushHand(spec.tip_beyond_tcp_m, spec.finger_width_m, spec.finger_thickness_m)
        floor_z = float(cell.bin.world_from_bin[2, 3])
        push = plan_push(last.plan, last.fits, last.normpositions, cell, hand, floor_z, opts.push_m)
        if push is None:
            log.warning("no feasible grasp and no push either: stopping")
            break
        try:
            path = push_motion(push, last.fits, last.normpositions, cell, driver.state().q)
        except PlanningError as exc:
            log.warning("the push has no arm path (%s): stopping", exc)
            break
        step(f"push {len(pushes) + 1}: no feasible grasp, pushing a part {opts.push_m * 100:.0f} cm")
        driver.gripper_close()
        driver.follow_trajectory(path.t, path.q)
        driver.gripper_open()
        layout = source.layout
        moved = simulate_push(
            list(zip(layout.templates, layout.world_from_object, strict=True)),
            layout.static_boxes,
            spec,
            push.world_from_tcp,
            push.push,
        )
        layout = replace(layout, world_from_object=np.asarray(moved.world_from_objects_final).reshape(-1, 4, 4))
        b = cell.bin
        local = np.einsum(
            "ij,nj->ni",
            np.linalg.inv(b.world_from_bin),
            np.c_[layout.world_from_object[:, :3, 3], np.ones(layout.n_parts)],
        )
        out = [i for i in range(layout.n_parts) if np.any(np.abs(local[i, :2]) > b.inner_size[:2] / 2.0)]
        source.layout = remove_parts(layout, out) if out else layout
        pushes.append(
            {
                "after_pick": len(records),
                "start_world_from_tcp": np.asarray(push.world_from_tcp).round(6).tolist(),
                "push_m": np.asarray(push.push).round(6).tolist(),
                "outcome": moved.outcome,
                "parts_out_of_bin": len(out),
            }
        )
    return records, pushes


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


def stop_reason(records: list[PickRecord], left: int) -> tuple[str, list[dict[str, Any]]]:
    """One line saying why the run ended, and per part the planner saw in the last frame its rejection counts and
    closest call (empty unless the last turn found no feasible grasp)."""
    if not records:
        return "no frames", []
    last = records[-1]
    plan = last.result.plan
    if last.status == "no_feasible_grasp":
        if plan is None:
            return f"no plan: nothing was perceived to pick ({left} part(s) left)", []
        if not plan.targets:
            if plan.uncovered_voxels and not last.result.instances:
                return f"{stop_line(plan)} ({left} part(s) left)", []
            fits = last.result.fits
            why = "; ".join(f"{f.template.name}: {f.reason}" for f in fits if not f.accepted)[:300]
            return (
                f"no feasible grasp: {len(last.result.instances)} instance(s) segmented, no template fit accepted "
                f"({why or 'no fit attempted'}); {left} part(s) left",
                [],
            )
        return stop_line(plan), [r.to_json() for r in rejections_by_target(plan)]
    if left == 0:
        return "the bin is empty", []
    if last.status in ("driver_fault", "unsafe_plan", "pick_failed") and last.fault:
        return f"{last.status}: {last.fault} ({left} part(s) left)", []
    return f"{last.status} after {len(records)} turn(s), the most picks allowed ({left} part(s) left)", []


def summarise(records: list[PickRecord], wall_s: float, driver: str, segmenter: str, left: int) -> dict[str, Any]:
    picked = sum(1 for r in records if r.status == "picked")
    why, parts = stop_reason(records, left)
    return {
        "picks_attempted": sum(1 for r in records if r.status in ("picked", "pick_failed")),
        "picks_succeeded": picked,
        "parts_left_in_bin": left,
        "stopped_because": records[-1].status if records else "no frames",
        "stop": why,
        "stop_parts": parts,
        "driver": driver,
        "segmenter": segmenter,
        "wall_time_s": round(wall_s, 2),
        "picks": [pick_row(r) for r in records],
    }


def write_report(
    out: Path, records: list[PickRecord], cell: CellConfig, segmenter: str, driver: str, left: int = 0
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
    why, parts = stop_reason(records, left)
    stop_html = f"<p>{html.escape(why)}</p>"
    if parts:
        stop_html += table_html(
            [
                {
                    "part": p["template"],
                    "rejected by reason": ", ".join(f"{k} {v}" for k, v in p["rejected_by_reason"].items()),
                    "closest call": f"{p['best_rejected']['id']} ({p['best_rejected']['reason']} "
                    f"at {p['best_rejected']['pose'] or '-'})",
                }
                for p in parts
            ]
        )
        last = records[-1]
        picture = frame_overlay(last.result)
        for p in parts:
            best = p["best_rejected"]
            picture = draw_overlay(
                picture,
                last.result.frame.camera,
                grasp_world_from_tcp=np.asarray(best["world_from_tcp"]),
                grasp_opening_m=float(best["opening_m"]),
            )
        images["Why it stopped: the closest rejected grasp of each part left"] = encode_png(picture)
    sections["Why it stopped"] = stop_html
    write_page(out / "report.html", report_page("normpos-grasp demo", twin, images, sections))
    files["report"] = out / "report.html"
    return files
