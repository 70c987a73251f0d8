"""Entry point of `normpos-grasp`: builds the argument parser from the command modules and maps errors to exit codes.

Each command module defines `register(subparsers)`, which adds its parser and sets `handler=run`, where
`run(args) -> int` returns the exit code.

Exit codes (every command):
    0    ok
    1    a result the user must act on (for example no feasible grasp)
    2    bad input or a library error: one line `normpos-grasp CMD: error: ...` on stderr
    3    an internal error (a bug): one line on stderr naming a log file that holds the traceback
    130  interrupted (Ctrl-C)
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import logging
import os
import sys
import tempfile
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from normpos_grasp import __version__
from normpos_grasp.errors import NormposError

#: folder of the internal-error logs (override with the environment variable NORMPOS_GRASP_LOG_DIR)
LOG_DIR_ENV = "NORMPOS_GRASP_LOG_DIR"


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line on stderr (exit 2), like every other input error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


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
    "replay",
    "teach",
)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="normpos-grasp",
        description="Measure objects in RGB-D frames, fit CAD templates, plan and execute grasps on UR arms.",
        epilog="exit codes: 0 ok; 1 a result to act on (e.g. no feasible grasp); 2 bad input (one line "
        f"'error: ...' on stderr); 3 internal error (traceback in a log file under ${LOG_DIR_ENV} or the temp "
        "folder); 130 interrupted",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"normpos_grasp.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version and usage errors (already printed): return the code
        return exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 2
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 2
    prog = f"normpos-grasp {args.command}"
    try:
        return int(handler(args))
    except NormposError as exc:
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a path that cannot be read or written: the user's input or environment
        print(f"{prog}: error: {_os_error(exc)}", file=sys.stderr)
        return 2
    except UnicodeDecodeError as exc:
        print(f"{prog}: error: an input file is not UTF-8 text ({exc.reason} at byte {exc.start})", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug: say so in one line, keep the traceback in a log file
        log_path = _write_crash_log(args.command, exc)
        where = f"traceback in {log_path}" if log_path is not None else "the traceback could not be saved"
        print(
            f"{prog}: internal error: {type(exc).__name__}: {_one_line(exc)} ({where}; please report it)",
            file=sys.stderr,
        )
        return 3


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _os_error(exc: OSError) -> str:
    reason = exc.strerror or _one_line(exc)
    names = [str(n) for n in (exc.filename, exc.filename2) if n is not None]
    return f"{' -> '.join(names)}: {reason}" if names else reason


def _write_crash_log(command: str, exc: BaseException) -> Path | None:
    """Write the traceback of `exc` to LOG_DIR/crash-<UTC time>-<pid>.log; returns the path or None on failure."""
    folder = Path(os.environ.get(LOG_DIR_ENV) or Path(tempfile.gettempdir()) / "normpos-grasp")
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%dT%H%M%SZ")
    path = folder / f"crash-{stamp}-{os.getpid()}.log"
    text = f"normpos-grasp {__version__} {command}\nargv: {sys.argv}\n\n" + "".join(
        traceback.format_exception(type(exc), exc, exc.__traceback__)
    )
    try:
        folder.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    except OSError:
        return None
    return path


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
