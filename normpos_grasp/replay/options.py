"""Frozen `*Options` dataclasses to JSON and back, exactly (floats keep every bit through JSON's repr), so a bundle
records every setting of the cycle, seeds included (fit RANSAC, depth-bias RANSAC, grasp synthesis, RRT).

Reading is strict: an unknown key is a `BundleError` (a foreign or newer bundle); a key the bundle lacks (written
by an older version) takes today's default and is reported in `missing`.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path
from types import UnionType
from typing import Any, TypeVar

from normpos_grasp.errors import InputError
from normpos_grasp.replay.errors import BundleError

T = TypeVar("T")


def options_to_json(value: Any) -> Any:
    """JSON-ready form of an options dataclass (nested dataclasses as objects, tuples as lists)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: options_to_json(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple | list):
        return [options_to_json(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise InputError(f"cannot record an option of type {type(value).__name__}: {value!r}")


def options_from_json(cls: type[T], data: Any, where: str = "options", missing: list[str] | None = None) -> T:
    """Rebuild `cls` (an options dataclass whose fields all have defaults) from `options_to_json` output.

    missing: receives the dotted names of fields the data lacked (they keep their defaults)."""
    if not isinstance(data, dict):
        raise BundleError(f"{where}: expected an object, got {type(data).__name__}")
    default = cls()
    names = {f.name for f in dataclasses.fields(default)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise BundleError(f"{where}: unknown option {unknown[0]!r} (a bundle of another version?)")
    hints: dict[str, Any] | None = None
    values: dict[str, Any] = {}
    for f in dataclasses.fields(default):  # type: ignore[arg-type]
        key = f"{where}.{f.name}"
        if f.name not in data:
            if missing is not None:
                missing.append(key)
            continue
        current = getattr(default, f.name)
        raw = data[f.name]
        kind: Any = type(current)
        if current is None and raw is not None:
            hints = hints if hints is not None else typing.get_type_hints(cls)
            kind = _non_none(hints[f.name])
        values[f.name] = _value(kind, raw, key, missing)
    try:
        return dataclasses.replace(default, **values)  # type: ignore[type-var]
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{where}: {exc}") from exc


def set_option(options: T, dotted: str, text: str) -> T:
    """A copy of `options` with the field at `dotted` ('plan.motion.seed') set to `text` parsed as JSON (bare
    words are strings). InputError naming the path for an unknown field or a value of the wrong type."""
    try:
        raw = json.loads(text)
    except ValueError:
        raw = text
    head, _, rest = dotted.partition(".")
    fields = {f.name for f in dataclasses.fields(options)}  # type: ignore[arg-type]
    if head not in fields:
        raise InputError(f"unknown option {dotted!r}: {type(options).__name__} has {', '.join(sorted(fields))}")
    current = getattr(options, head)
    if rest:
        if not dataclasses.is_dataclass(current):
            raise InputError(f"option {head!r} is a value, not a group: cannot set {dotted!r}")
        new = set_option(current, rest, text)
    else:
        if dataclasses.is_dataclass(current):
            raise InputError(f"option {dotted!r} is a group: set one of its fields ({dotted}.NAME=VALUE)")
        try:
            new = _value(type(current), raw, dotted, None) if current is not None else raw
        except BundleError as exc:
            raise InputError(str(exc)) from exc
    try:
        return dataclasses.replace(options, **{head: new})  # type: ignore[type-var]
    except (TypeError, ValueError) as exc:
        raise InputError(f"option {dotted}={text}: {exc}") from exc


def _non_none(hint: Any) -> Any:
    if isinstance(hint, UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return hint


def _value(kind: Any, raw: Any, where: str, missing: list[str] | None) -> Any:
    if raw is None:
        return None
    if isinstance(kind, type) and dataclasses.is_dataclass(kind):
        return options_from_json(kind, raw, where, missing)
    if kind is bool:
        if not isinstance(raw, bool):
            raise BundleError(f"{where}: expected true or false, got {raw!r}")
        return raw
    if kind is int:
        if isinstance(raw, bool) or not isinstance(raw, int):
            raise BundleError(f"{where}: expected a whole number, got {raw!r}")
        return raw
    if kind is float:
        if isinstance(raw, bool) or not isinstance(raw, int | float):
            raise BundleError(f"{where}: expected a number, got {raw!r}")
        return float(raw)
    if kind is str:
        if not isinstance(raw, str):
            raise BundleError(f"{where}: expected text, got {raw!r}")
        return raw
    if kind is tuple:
        if not isinstance(raw, list):
            raise BundleError(f"{where}: expected a list, got {raw!r}")
        return tuple(raw)
    if kind is Path:
        return Path(str(raw))
    return raw
