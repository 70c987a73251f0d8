"""`normpos-grasp view --report DIR [--port P]`: serve a report folder's 3D twin as a live page on 127.0.0.1.

The folder's `scene.glb` (written by `demo` and by `run --out DIR`) is shown in the browser and re-read whenever it
changes, so `normpos-grasp run ... --out DIR` in one terminal and `normpos-grasp view --report DIR` in another
follows a running cell; `summary.json` / `run.json` are shown beside the scene. Ctrl-C stops serving.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from normpos_grasp.cli.args import float_in


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "view",
        help="serve a report folder's 3D twin (scene.glb) as a live web page on 127.0.0.1",
        description="Serve the 3D scene of a report folder (from `demo` or `run --out`) in the browser; the page "
        "follows the folder while a run keeps writing it.",
    )
    p.add_argument("--report", type=Path, required=True, help="report folder holding scene.glb")
    p.add_argument("--port", type=int, default=8765, help="port on 127.0.0.1 (0: any free port)")
    p.add_argument(
        "--poll", type=float_in(0.05, 60.0, "s"), default=1.0, help="seconds between checks for a changed scene.glb"
    )
    p.add_argument(
        "--seconds", type=float_in(0.0, 1e6, "s"), default=0.0, help="stop after this many seconds (0: until Ctrl-C)"
    )
    p.set_defaults(handler=run)


def _read_state(folder: Path) -> dict[str, Any]:
    for name in ("summary.json", "run.json"):
        path = folder / name
        if path.is_file():
            try:
                data = json.loads(path.read_text())
            except ValueError:
                continue  # being rewritten: keep the last one
            return {"report": str(folder), "file": name, **(data if isinstance(data, dict) else {"data": data})}
    return {"report": str(folder)}


def run(args: argparse.Namespace) -> int:
    from normpos_grasp.errors import InputError
    from normpos_grasp.report.live import LiveView
    from normpos_grasp.report.scene3d import TwinScene

    folder: Path = args.report
    glb = folder / "scene.glb"
    if not glb.is_file():
        raise InputError(f"{folder} has no scene.glb: give a folder written by `normpos-grasp demo` or `run --out`")
    with LiveView(port=args.port, title=f"normpos-grasp view: {folder.name}") as view:
        stamp = glb.stat().st_mtime_ns
        view.publish(TwinScene.from_glb(glb), _read_state(folder))
        print(f"serving {glb} at {view.url} (Ctrl-C stops)", flush=True)
        end = time.monotonic() + args.seconds if args.seconds > 0 else float("inf")
        while time.monotonic() < end:
            time.sleep(min(args.poll, max(0.0, end - time.monotonic())))
            try:
                current = glb.stat().st_mtime_ns
            except FileNotFoundError:
                continue  # being replaced
            if current != stamp:
                stamp = current
                try:
                    view.publish(TwinScene.from_glb(glb), _read_state(folder))
                except InputError as exc:  # half-written file: try again next poll
                    print(f"view: {exc}", flush=True)
    return 0
