"""`normpos-grasp run --cell CELL.yaml --source SOURCE --robot HOST [--execute] [--view]`: the cell loop.

capture -> segment -> measure -> fit -> plan -> (execute) -> check the pick, repeated until the source is exhausted,
nothing is feasible, the driver faults or --max-picks turns. Dry run by default: every plan is checked against the
cell's safety limits and nothing is sent. SOURCE: a BOP scene or split folder, `synthetic[:N]` (a physics-settled
bin of N parts in the cell), or `realsense` (optional pyrealsense2 extra). docs/loop.md.

Exit codes: 0 at least one pick planned (and executed with --execute), 1 no feasible grasp in the first frame or a
pick failed (also: grip not detected after closing), 2 bad input, a controller that is not the cell's robot, a
driver fault or an unsafe plan, 130 SIGINT (Ctrl-C) and 143 SIGTERM: the arm is stopped (stopJ) before the client
disconnects, on every way out.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.cli.args import add_library_args, float_in

SEGMENTERS = ("model", "depth", "gt")


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "run",
        help="the cell loop: capture, measure, fit, plan and (with --execute) pick, repeatedly",
        description="Run the pick loop of a cell on a frame source. Dry run unless --execute: plans are checked "
        "against the safety limits and nothing is sent to the robot. With --execute the controller's robot model "
        "must be the cell's; SIGINT/SIGTERM stop the arm before the client disconnects.",
        epilog="exit codes: 0 picks planned/picked, 1 no feasible grasp or a pick failed, 2 bad input / controller "
        "mismatch / driver fault / unsafe plan, 130 SIGINT, 143 SIGTERM (the arm is stopped first)",
    )
    p.add_argument("--cell", required=True, help="cell YAML (docs/cells.md) or a packaged cell name")
    p.add_argument(
        "--source", required=True, help="BOP scene/split folder, 'synthetic[:N]' (N parts, default 6) or 'realsense'"
    )
    p.add_argument(
        "--robot",
        required=True,
        help="UR controller address (127.0.0.1 for `normpos-grasp emulate-ur`), or 'sim' for the simulated driver",
    )
    p.add_argument("--execute", action="store_true", help="send the plans to the robot (default: dry run)")
    p.add_argument(
        "--robot-serial", default=None, help="with --execute: refuse a controller whose serial number differs"
    )
    p.add_argument("--view", action="store_true", help="serve a live 3D view of the cell on 127.0.0.1")
    p.add_argument("--view-port", type=int, default=8765, help="port of the live view (0: any free port)")
    p.add_argument("--max-picks", type=int, default=20, help="most loop turns")
    p.add_argument(
        "--segmenter",
        choices=SEGMENTERS,
        default=None,
        help="instance source: model (bundled ONNX), depth (model-free) or gt (BOP masks / synthetic truth); "
        "default: gt for BOP and synthetic sources, model for a camera",
    )
    add_library_args(p, "the built-in parts for synthetic sources and normpos_grasp BOP data, else the cell templates")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic bin")
    p.add_argument("--sensor", default="d435", help="depth-noise preset of the synthetic bin")
    p.add_argument("--parts", default="", help="comma-separated part names for the synthetic bin (default: all)")
    p.add_argument(
        "--no-home",
        action="store_true",
        help="with --execute: plan from where the arm is instead of moving to the cell's home first",
    )
    p.add_argument(
        "--arrive-tol", type=float_in(1e-5, 0.05, "rad"), default=1e-3, help="joint tolerance for a finished move, rad"
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for plan_NN.json, run.json and the current frame's "
        "scene.glb (watch it with `normpos-grasp view --report OUT`)",
    )
    p.add_argument(
        "--bundles",
        type=Path,
        default=None,
        metavar="DIR",
        help="save a replay bundle of every turn under DIR (`normpos-grasp replay BUNDLE`; docs/replay.md)",
    )
    p.add_argument(
        "--linger",
        type=float_in(0.0, 1e5, "s"),
        default=0.0,
        help="with --view: keep serving this many seconds at the end",
    )
    p.add_argument(
        "--overlap",
        action="store_true",
        help="perceive and plan the next frame while the arm places (once it passed the retreat); docs/loop.md",
    )
    p.set_defaults(handler=run)


def arm_state_dict(state: Any, world_from_base: Any) -> dict[str, Any]:
    """JSON-ready arm state for the live view: joints (rad), TCP in the world (m, rotation matrix), modes."""
    world_from_tcp = np.asarray(world_from_base) @ np.asarray(state.base_from_tcp)
    return {
        "joints_rad": [round(float(v), 5) for v in state.q],
        "joint_speeds_rad_s": [round(float(v), 4) for v in state.qd],
        "tcp_xyz_m": [round(float(v), 5) for v in world_from_tcp[:3, 3]],
        "tcp_rotation": np.round(world_from_tcp[:3, :3], 4).tolist(),
        "robot_mode": int(state.robot_mode),
        "safety_mode": int(state.safety_mode),
        "protective_stop": bool(state.protective_stopped),
        "emergency_stop": bool(state.emergency_stopped),
        "program_running": bool(state.program_running),
        "controller_time_s": round(float(state.timestamp), 3),
    }


def _source(args: argparse.Namespace, cell: Any) -> tuple[Any, Any, Any, str]:
    """(source, template library, segmenter, source kind)."""
    from normpos_grasp.cli.args import library_paths
    from normpos_grasp.errors import InputError
    from normpos_grasp.loop import BopFrameSource, SyntheticBinSource
    from normpos_grasp.perception.factory import library_model
    from normpos_grasp.pipeline import make_segmenter
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.templates.library import resolve_library

    models = library_paths(args)
    text = str(args.source)
    if text == "synthetic" or text.startswith("synthetic:"):
        count_text = text.partition(":")[2] or "6"
        try:
            count = int(count_text)
        except ValueError as exc:
            raise InputError(f"--source synthetic:N needs a whole number of parts, got {count_text!r}") from exc
        if count < 1:
            raise InputError(f"--source synthetic:N needs at least one part, got {count}")
        library = list(resolve_library(models))
        wanted = tuple(n for n in (args.parts or "").split(",") if n)
        source: Any = SyntheticBinSource(cell, count, args.seed, args.sensor, library, parts=wanted)
        kind = args.segmenter or "gt"
        if kind == "gt":
            segmenter: Any = source.ground_truth_segmenter()
        else:
            segmenter = make_segmenter(kind, library_model(models))
        return source, library, segmenter, "synthetic"
    if text == "realsense":
        from normpos_grasp.realsense_source import RealSenseSource

        kind = args.segmenter or "model"
        if kind == "gt":
            raise InputError("--segmenter gt needs ground truth: use a BOP or synthetic source")
        if not models and cell.templates_path is None:
            raise InputError("no template library: pass --library or set `templates` in the cell file")
        camera_source = RealSenseSource(cell.world_from_camera)
        try:
            paths = models or (str(cell.templates_path),)
            library = list(resolve_library(paths))
            return camera_source, library, make_segmenter(kind, library_model(paths)), "camera"
        except BaseException:
            camera_source.close()
            raise
    path = Path(text)
    if not path.is_dir():
        raise InputError(f"--source {text!r} is neither a folder, 'synthetic[:N]' nor 'realsense'")
    bop = BopFrameSource(path, cell.world_from_camera)
    names = bop.part_names()
    if models:
        library = list(resolve_library(models))
    elif names:
        by_name = {t.name: t for t in default_part_library()}
        library = [by_name[n] for n in dict.fromkeys(names.values()) if n in by_name]
    elif cell.templates_path is not None:
        library = list(resolve_library((str(cell.templates_path),)))
    else:
        raise InputError("no template library: pass --library or set `templates` in the cell file")
    if not library:
        raise InputError(f"the template library for {path} is empty")
    kind = args.segmenter or "gt"
    segmenter = bop.ground_truth_segmenter(names) if kind == "gt" else make_segmenter(kind, library_model(models))
    return bop, library, segmenter, "bop"


def run(args: argparse.Namespace) -> int:
    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.errors import InputError
    from normpos_grasp.execution import DriverOptions, SafetyLimits, SimDriver, SupervisedRtdeDriver, stop_signals
    from normpos_grasp.execution.gripper_config import gripper_io, tool_driver
    from normpos_grasp.execution.interrupts import exit_code, signal_name
    from normpos_grasp.loop import PickRecord, run_cell_loop
    from normpos_grasp.pipeline import FrameResult
    from normpos_grasp.report.frame import frame_twin

    if args.max_picks < 1:
        raise InputError(f"--max-picks must be at least 1, got {args.max_picks}")
    cell = resolve_cell(args.cell)
    t_start = time.perf_counter()
    source, library, segmenter, source_kind = _source(args, cell)
    limits = SafetyLimits.from_cell(cell)
    driver: Any = None
    tool: Any = None  # the cell's gripper driver (gripper.driver), connected after the arm
    before_execute: Any = None
    view: Any = None
    bundles: Any = None
    out: Path | None = args.out
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    mode = "execute" if args.execute else "dry run"
    watch_state: dict[str, Any] = {"zones": [z.name for z in cell.watch.zones] if cell.watch else [], "events": []}
    last_twin: list[Any] = []

    def on_watch_event(event: Any) -> None:
        """A zone stop: listed in the live view's state, its blobs drawn into the twin."""
        from types import SimpleNamespace

        from normpos_grasp.report.live import add_watch_overlay

        watch_state["events"].append(event.to_dict())
        if view is not None and last_twin and cell.watch is not None:
            labels = [i.get("label", "object") for i in event.intrusions]
            blobs = [SimpleNamespace(label=lb, points=pt) for lb, pt in zip(labels, event.points, strict=True)]
            add_watch_overlay(last_twin[-1], (), blobs)
            view.publish(last_twin[-1])

    with stop_signals():
        try:
            try:
                from normpos_grasp.cli.run_watch import make_cell_watch

                cell_watch = make_cell_watch(args, cell, source, source_kind, on_watch_event)
                if args.execute:
                    options = DriverOptions(arrive_tol_rad=args.arrive_tol)
                    spec = cell.gripper_driver
                    if args.robot == "sim" and len(cell.tools) > 1:
                        # a dual-tool flange: each plan's tool gets its own outputs (the cup's vacuum, the jaws')
                        driver = SimDriver(limits, q_home=np.asarray(cell.home_q, dtype=np.float64), options=options)
                        from normpos_grasp.loop import tool_outputs_hook

                        before_execute = tool_outputs_hook(cell, driver)
                    elif args.robot == "sim":
                        if spec is not None:
                            print(
                                f"gripper.driver ({spec.kind}) is not used with --robot sim (no controller I/O): the "
                                "source's check judges each pick",
                                flush=True,
                            )
                        driver = SimDriver(limits, q_home=np.asarray(cell.home_q, dtype=np.float64), options=options)
                    else:
                        cell.refuse_dual_tool(f"the controller at {args.robot}")
                        driver = SupervisedRtdeDriver(
                            args.robot,
                            limits,
                            gripper_io(spec),
                            options=options,
                            expected_serial=args.robot_serial,
                        )
                        tool = tool_driver(spec, driver, args.robot)
                        before_execute = emulated_part_hook(source, cell, args.robot, spec)
                    driver.connect()
                    if tool is not None:
                        tool.connect()  # a Robotiq activates (and calibrates) before the arm moves
                    if not args.no_home:
                        speed = min(1.0, float(np.min(cell.motion.joint_velocity)))
                        accel = min(2.0, float(np.min(cell.motion.joint_acceleration)))
                        driver.move_joints(np.asarray(cell.home_q)[None], speed, accel)
                if args.view:
                    from normpos_grasp.report.live import LiveView

                    view = LiveView(port=args.view_port, title=f"normpos-grasp run: {cell.name}").start()
                    print(f"live view: {view.url}", flush=True)
                    if driver is not None:
                        view.follow(
                            lambda: {
                                "mode": mode,
                                **arm_state_dict(driver.state(), cell.world_from_base),
                                **({"watch": watch_state} if cell.watch is not None else {}),
                            }
                        )
                    else:
                        view.publish(None, {"mode": mode, "joints_rad": [float(v) for v in cell.home_q]})

                def on_plan(result: FrameResult) -> None:
                    if bundles is not None:
                        bundles.wait()  # the previous turn's bundle is written before this plan moves the arm
                    if view is None and out is None:
                        return
                    scene = frame_twin(result, cell, candidates=True)
                    if cell.watch is not None:
                        from normpos_grasp.report.live import add_watch_overlay

                        add_watch_overlay(scene, cell.watch.zones)
                        last_twin[:] = [scene]
                    if view is not None:
                        view.publish(scene, None if driver is not None else _dry_state(result, mode))
                    if out is not None:
                        scene.export_glb(out / "scene.glb")  # `normpos-grasp view --report OUT` follows it

                done_so_far: list[PickRecord] = []

                def on_pick(record: PickRecord) -> None:
                    doc = record.plan_json or {}
                    target = (doc.get("target") or {}).get("template", "-")
                    grasp = (doc.get("grasp") or {}).get("id", "-")
                    cands = doc.get("candidates") or {}
                    ms = ", ".join(f"{k} {v:.0f}" for k, v in record.timings_ms.items())
                    print(
                        f"pick {record.index + 1}: {record.status} ({record.check}); target {target}, grasp {grasp}; "
                        f"{cands.get('feasible', 0)} feasible of {cands.get('total', 0)} candidates; ms: {ms}",
                        flush=True,
                    )
                    if record.fault:
                        print(f"  fault: {record.fault}", flush=True)
                    if record.status == "no_feasible_grasp" and cands.get("rejected_by_reason"):
                        reasons = sorted(cands["rejected_by_reason"].items(), key=lambda kv: -kv[1])
                        print("  rejected: " + ", ".join(f"{k} {v}" for k, v in reasons), flush=True)
                    if record.status == "no_feasible_grasp" and doc.get("uncovered_voxels"):
                        print(
                            f"  {doc['uncovered_voxels']} clutter voxels of surfaces no instance covers remain in the "
                            "bin: parts the segmenter did not find?",
                            flush=True,
                        )
                    if out is not None:
                        if record.plan_json is not None:
                            _write_json(out / f"plan_{record.index + 1:02d}.json", record.plan_json)
                        done_so_far.append(record)  # run.json grows pick by pick (`normpos-grasp view` shows it)
                        _write_json(
                            out / "run.json", _run_summary(cell.name, args, source_kind, mode, done_so_far, t_start)
                        )

                if args.bundles is not None:
                    from normpos_grasp.replay.bundle import BundleRecorder

                    bundles = BundleRecorder(  # written in the background: the next turn does not wait
                        args.bundles,
                        segmenter,
                        library_sources=_library_sources(args, cell, library),
                        driver=driver,
                        background=True,
                    )
                records = run_cell_loop(
                    cell,
                    source,
                    segmenter,
                    library,
                    driver,
                    execute=bool(args.execute),
                    max_picks=args.max_picks,
                    on_pick=on_pick,
                    on_plan=on_plan,
                    gripper=tool,
                    before_execute=before_execute,
                    bundles=bundles,
                    watch=cell_watch,
                    overlap=bool(args.overlap),
                )
                if view is not None and args.linger > 0:
                    time.sleep(args.linger)
            finally:
                if bundles is not None:
                    bundles.close()
                if view is not None:
                    view.close()
                if tool is not None:
                    tool.disconnect()
                if driver is not None:
                    driver.disconnect()
                    if isinstance(driver, SimDriver):
                        driver.shutdown()
                close = getattr(source, "close", None)
                if callable(close):
                    close()
        except KeyboardInterrupt as exc:
            code = exit_code(exc)
            print(
                f"normpos-grasp run: interrupted by {signal_name(exc)}: arm stopped, nothing further sent "
                f"(exit {code})",
                file=sys.stderr,
                flush=True,
            )
            return code
    statuses = [r.status for r in records]
    summary = _run_summary(cell.name, args, source_kind, mode, records, t_start)
    if out is not None:
        _write_json(out / "run.json", summary)
    done = sum(1 for s in statuses if s in ("picked", "dry_run"))
    print(
        f"{mode}: {done} of {len(records)} turns planned{' and picked' if args.execute else ''}; "
        f"{summary['wall_time_s']} s"
    )
    if bundles is not None:
        print(f"{len(bundles.saved)} replay bundles in {args.bundles} (normpos-grasp replay BUNDLE)")
    if any(s in ("driver_fault", "unsafe_plan") for s in statuses):
        return 2
    if done == 0 or "pick_failed" in statuses:
        return 1
    return 0


def _library_sources(args: argparse.Namespace, cell: Any, library: Any) -> tuple[str, ...]:
    """The `resolve_library` entries the run's templates come from, for replay bundles: --library, else none for
    the built-in parts, else the cell's templates."""
    from normpos_grasp.cli.args import library_paths
    from normpos_grasp.replay.bundle import template_sha256
    from normpos_grasp.templates.library import builtin_library

    paths = library_paths(args)
    if paths:
        return paths
    builtin = {t.name: template_sha256(t) for t in builtin_library()}
    if all(builtin.get(t.name) == template_sha256(t) for t in library):
        return ()
    return (str(cell.templates_path),) if cell.templates_path is not None else ()


def emulated_part_hook(source: Any, cell: Any, robot: str, spec: Any) -> Any:
    """For a synthetic bin picked on the loopback controller with a Robotiq: before each plan is sent, put the true
    part in the emulated gripper (`emu gripper part`): its width across the fingers is the true mesh's section in the
    plane of the grasp TCP (no section: nothing between the fingers, the gripper closes on nothing), placed where
    the controller's TCP (the flange: the loopback controller has no TCP offset set) will be at the grasp, caught
    within 2 cm of it. None when any of the three does not apply."""
    from normpos_grasp.cell.gripper_driver import RobotiqDriverSpec
    from normpos_grasp.hosts import is_ipv4_loopback_literal
    from normpos_grasp.loop import SyntheticBinSource
    from normpos_grasp.sim.ur_emulator.process import dashboard_request

    if not (isinstance(source, SyntheticBinSource) and isinstance(spec, RobotiqDriverSpec)):
        return None
    if not is_ipv4_loopback_literal(robot):
        return None

    def put_part(plan: Any) -> None:
        width = None
        part = source.true_part_of(plan)
        if part >= 0 and plan.chosen is not None:
            world_from_tcp = np.asarray(plan.chosen.candidate.world_from_tcp, dtype=np.float64)
            mesh = source.layout.templates[part].mesh.copy().apply_transform(source.layout.world_from_object[part])
            section = mesh.section(plane_origin=world_from_tcp[:3, 3], plane_normal=world_from_tcp[:3, 2])
            if section is not None and len(section.vertices):
                x = (np.asarray(section.vertices) - world_from_tcp[:3, 3]) @ world_from_tcp[:3, 0]
                width = float(np.max(x) - np.min(x))
        if width is None or not 0.0 < width < 1.0:
            dashboard_request(robot, "emu gripper part none")
            return
        base_from_flange = (
            np.linalg.inv(cell.world_from_base)
            @ np.asarray(plan.chosen.candidate.world_from_tcp)
            @ np.linalg.inv(cell.tool.flange_from_tcp)
        )
        xyz = " ".join(f"{v:.6f}" for v in base_from_flange[:3, 3])
        dashboard_request(robot, f"emu gripper part {width:.5f} {xyz} 0.02")

    return put_part


def _run_summary(
    cell: str, args: argparse.Namespace, source_kind: str, mode: str, records: list[Any], t_start: float
) -> dict[str, Any]:
    return {
        "cell": cell,
        "source": str(args.source),
        "source_kind": source_kind,
        "mode": mode,
        "picks": [
            {"pick": r.index + 1, "status": r.status, "check": r.check, "fault": r.fault, "timings_ms": r.timings_ms}
            for r in records
        ],
        "wall_time_s": round(time.perf_counter() - t_start, 3),
    }


def _write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (a reader never sees half a file)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)


def _dry_state(result: Any, mode: str) -> dict[str, Any]:
    plan = result.plan
    state: dict[str, Any] = {"mode": mode, "plan": plan.status if plan is not None else "none"}
    if plan is not None and plan.waypoints:
        state["joints_rad"] = [round(float(v), 5) for v in plan.waypoints[0].q]
        state["waypoints"] = [w.name for w in plan.waypoints]
    return state
