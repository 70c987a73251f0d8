"""`normpos-grasp replay BUNDLE [--out DIR] [--set KEY=VALUE ...] [--library DIR]`: re-run a saved cycle offline.

Perception and planning run again on the bundle's frame with its recorded cell, options (seeds included), start
joints and templates; one table shows what differs (masks IoU, fit pose deltas in mm / deg, the plan: grasp
chosen, joint waypoints and trajectory max |dq|, plan JSON bytes). docs/replay.md.

Exit codes: 0 identical (the plan JSON byte for byte, without its wall-clock timing_ms), 1 something differs, 2 bad
input (not a bundle, a corrupt or unfinished one, an unknown option): one line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "replay",
        help="re-run a replay bundle's perception and planning offline and show what differs",
        description="Re-run the perception and planning of one saved cycle (a bundle written by `run --bundles`) "
        "with its recorded cell, options and seeds, and compare with the recording.",
        epilog="exit codes: 0 identical, 1 different, 2 bad input (not a bundle, corrupt, unknown option)",
    )
    p.add_argument("bundle", type=Path, help="the bundle folder")
    p.add_argument(
        "--out", type=Path, default=None, help="write replay.json (the table), plan.json and scene.glb of the replay"
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="replay with one recorded option changed, e.g. plan.motion.seed=3 (repeatable; VALUE is JSON)",
    )
    p.add_argument(
        "--library",
        "--models",
        dest="library",
        action="append",
        metavar="DIR",
        default=None,
        help="load the templates from these libraries instead of the recorded ones",
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from normpos_grasp.atomic import atomic_write_text
    from normpos_grasp.errors import InputError
    from normpos_grasp.replay.bundle import load_bundle
    from normpos_grasp.replay.options import set_option
    from normpos_grasp.replay.replay import replay_bundle

    bundle = load_bundle(args.bundle)
    options = bundle.options
    for item in args.overrides:
        key, sep, value = str(item).partition("=")
        if not sep or not key:
            raise InputError(f"--set needs KEY=VALUE, got {item!r}")
        options = set_option(options, key.strip(), value.strip())
    report = replay_bundle(bundle, options=options, models=tuple(args.library or ()))
    print(f"replay of {bundle.path} (cycle {int(bundle.cycle.get('index', 0)) + 1}, {bundle.cycle.get('status')})")
    print(report.table())
    for note in report.notes:
        print(f"note: {note}")
    print("identical" if report.identical else "DIFFERENT")
    if args.out is not None:
        from normpos_grasp.report.frame import frame_twin

        out: Path = args.out
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "replay.json", json.dumps(report.to_json(), indent=1))
        atomic_write_text(out / "plan.json", json.dumps(report.plan_json, indent=1))
        frame_twin(report.result, bundle.cell, candidates=True).export_glb(out / "scene.glb")
    return 0 if report.identical else 1
