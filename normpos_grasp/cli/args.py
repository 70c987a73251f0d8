"""Shared argument checks of the CLI commands: bounded numbers and output paths that never clobber an earlier run.

The bounded types raise `argparse.ArgumentTypeError`, which the parser turns into one line
`normpos-grasp CMD: error: argument --x: must be an integer in LO..HI, got V` and exit code 2.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from normpos_grasp.errors import InputError

#: help text of every `--overwrite` flag
OVERWRITE_HELP = "replace the results of an earlier run in --out (without it an existing output is refused)"


def int_in(lo: int, hi: int) -> Callable[[str], int]:
    """argparse type: an integer in [lo, hi]."""

    def parse(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer in {lo}..{hi}, got {text!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in {lo}..{hi}, got {value}")
        return value

    parse.__name__ = f"integer in {lo}..{hi}"
    return parse


def float_in(lo: float, hi: float, unit: str = "") -> Callable[[str], float]:
    """argparse type: a finite float in [lo, hi] (`unit` is only named in the message)."""
    suffix = f" {unit}" if unit else ""

    def parse(text: str) -> float:
        try:
            value = float(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number in [{lo}, {hi}]{suffix}, got {text!r}") from None
        if not math.isfinite(value) or not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be a number in [{lo}, {hi}]{suffix}, got {text!r}")
        return value

    parse.__name__ = f"number in [{lo}, {hi}]"
    return parse


def part_names(text: str, flag: str = "--parts") -> tuple[str, ...]:
    """Comma-separated part names; () for '' or 'default' (every part of the library). InputError for a list that
    names none (',,': a script's empty variable), so it is never read as 'all parts'."""
    if text.strip() in ("", "default"):
        return ()
    names = tuple(p.strip() for p in text.split(",") if p.strip())
    if not names:
        raise InputError(f"{flag}: {text!r} names no part; give comma-separated part names or 'default'")
    return names


def check_out_dir(path: Path, overwrite: bool) -> Path:
    """Validate an output folder without creating it: not a file; empty or absent unless `overwrite`.

    Raises InputError naming the path and the flag to pass; returns `path`.
    """
    if path.exists() and not path.is_dir():
        raise InputError(f"--out {path} is an existing file; give a folder (it is created when needed)")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise InputError(
            f"--out {path} already holds files (an earlier run?); pass --overwrite to replace them "
            "or choose an empty folder"
        )
    return path


def check_out_file(path: Path, overwrite: bool) -> Path:
    """Validate an output file path without creating anything: not a folder; absent unless `overwrite`."""
    if path.is_dir():
        raise InputError(f"--out {path} is a folder; give the name of the file to write")
    if path.exists() and not overwrite:
        raise InputError(f"--out {path} already exists; pass --overwrite to replace it")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise InputError(f"--out {path}: {parent} is a file, not a folder")
    return path


#: help text of every `--segmenter` flag
SEGMENTER_HELP = (
    "instance source: model (the bundled ONNX model, or --seg-model), depth (model-free; the template fit names the "
    "part), cad (the library's CAD templates found in the whole bin or table top, no masks), gt (the data's true "
    "masks: measures everything after segmentation), auto (model when its classes cover the library, else depth)"
)


def add_segmenter_args(parser: argparse.ArgumentParser, default: str) -> None:
    """The same two flags in every command that segments: --segmenter KIND and --seg-model PATH."""
    from normpos_grasp.perception.factory import SEGMENTER_KINDS

    parser.add_argument(
        "--segmenter", choices=SEGMENTER_KINDS, default=default, help=f"{SEGMENTER_HELP} (default {default})"
    )
    parser.add_argument(
        "--seg-model",
        "--model",
        "--onnx",
        dest="seg_model",
        metavar="ONNX",
        type=Path,
        default=None,
        help="ONNX segmentation model for --segmenter model/auto (default: the bundled one); "
        "--model and --onnx are older spellings",
    )


#: help text of every `--library` flag
LIBRARY_HELP = (
    "part library: a folder of templates (template.yaml + mesh, e.g. made by `teach`), one template folder, a BOP "
    "models folder (models_info.json + obj_XXXXXX.ply) or 'builtin' (the eight built-in parts); repeat to mix "
    "libraries (for example --library builtin --library my_parts)"
)


def add_library_args(parser: argparse.ArgumentParser, default_help: str = "the built-in parts") -> None:
    """The same `--library DIR` flag (repeatable; `--models` is the older spelling) in every command that makes or
    uses scenes; read it back with `library_from_args`."""
    parser.add_argument(
        "--library",
        "--models",
        dest="library",
        action="append",
        metavar="DIR",
        default=None,
        help=f"{LIBRARY_HELP}; default: {default_help}",
    )


def library_paths(args: argparse.Namespace) -> tuple[str, ...]:
    """The `--library` entries of `args`, in order (empty when none was given)."""
    return tuple(str(p) for p in (getattr(args, "library", None) or ()))


def seg_model_from_args(args: argparse.Namespace, fallback: str | Path | None = None) -> Path | None:
    """The segmentation model a command uses: `--seg-model`, else the one stored with its `--library` folders (or
    with `fallback` when none is given, as `library_from_args`): LIBRARY/segmenter/normpos_seg.onnx, made by `teach
    --segmenter-budget-min` (`perception.factory.library_model`); else None (the bundled model)."""
    from normpos_grasp.perception.factory import library_model

    given = getattr(args, "seg_model", None)
    if given is not None:
        return Path(given)
    paths = library_paths(args) or ((str(fallback),) if fallback is not None else ())
    return library_model(paths)


def library_from_args(args: argparse.Namespace, fallback: str | Path | None = None) -> Any:
    """The command's `TemplateLibrary` (templates.library.resolve_library): the `--library` entries, else
    `fallback` (for example a cell's templates), else the built-in parts."""
    from normpos_grasp.templates.library import resolve_library

    paths = library_paths(args)
    if not paths and fallback is not None:
        paths = (str(fallback),)
    return resolve_library(paths)
