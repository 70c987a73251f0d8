"""Entry point of `normpos-grasp`: builds the argument parser from the command modules and maps errors to exit codes.

Each command module defines `register(subparsers)`, which adds its parser and sets `handler=run`, where
`run(args) -> int` returns the exit code. Exit codes: 0 ok, 1 a result the user must act on (for example
no feasible grasp), 2 bad input or a library error, 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from normpos_grasp import __version__
from normpos_grasp.errors import NormposError

# command name -> module under normpos_grasp.cli
COMMAND_MODULES: tuple[str, ...] = (
    "calibrate",
    "measure",
    "synth",
    "train_segmenter",
    "estimate",
    "plan",
    "execute",
    "run",
    "emulate_ur",
    "demo",
    "view",
    "simulate",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="normpos-grasp",
        description="Measure objects in RGB-D frames, fit CAD templates, plan and execute grasps on UR arms.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"normpos_grasp.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 2
    try:
        return int(handler(args))
    except NormposError as exc:
        print(f"normpos-grasp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"normpos-grasp {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
