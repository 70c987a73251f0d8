"""The cell YAML's `gripper.driver` section: how the gripper is driven and how a grip is detected.

Three kinds (docs/cells.md): `robotiq` (a Robotiq 2F-85 / 2F-140 over the URCap's socket on the controller: the plan's
opening is commanded, object detection is the grip detection), `io` (digital outputs close / open it, a digital
input reports the grip) and `vacuum` (an output sucks, a digital input or a standard analog input with a threshold
reports the vacuum level). Every key is checked; errors are `CellConfigError`s naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from difflib import get_close_matches
from typing import Any

import numpy as np

from normpos_grasp.errors import CellConfigError

# digital outputs: standard 0-7, configurable 8-15 (tool outputs 0-1); inputs: bits 0-17 as RTDE reports them
_N_OUTPUTS, _N_TOOL_OUTPUTS, _N_INPUT_BITS = 16, 2, 18
_ROBOTIQ_KEYS = (
    "type",
    "model",
    "port",
    "speed",
    "force",
    "open_counts",
    "closed_counts",
    "calibrate",
    "activation_timeout_s",
    "move_timeout_s",
)
_IO_KEYS = ("type", "close_output", "open_output", "grip_input", "tool_outputs", "settle_s")
_VACUUM_KEYS = ("type", "vacuum_output", "release_output", "tool_outputs", "level_input", "settle_s")
_LEVEL_KEYS = ("digital", "analog", "threshold", "held_when")
ROBOTIQ_STROKES_M = {"2F-85": 0.085, "2F-140": 0.140}  # Robotiq's specifications


@dataclass(frozen=True)
class RobotiqDriverSpec:
    """A Robotiq 2F gripper behind the URCap socket of the arm's controller (host: the robot's address).

    model: '2F-85' or '2F-140'; stroke_m: its full opening, m. port: the URCap socket (63352). speed, force: 0
    (minimum) ... 255 (maximum) in the gripper's units. open_counts / closed_counts: the position register (0-255)
    at full opening and fully closed (the calibrated ends: the opening maps linearly between them); calibrate:
    measure both ends at activation instead (the fingers must be empty). activation_timeout_s, move_timeout_s: bounds
    on activation and on one finger motion, s."""

    model: str = "2F-85"
    stroke_m: float = 0.085
    port: int = 63352
    speed: int = 255
    force: int = 100
    open_counts: int = 0
    closed_counts: int = 255
    calibrate: bool = False
    activation_timeout_s: float = 5.0
    move_timeout_s: float = 3.0
    kind: str = "robotiq"


@dataclass(frozen=True)
class IODriverSpec:
    """A gripper on digital outputs: close_output high closes it, open_output high opens it (None: close_output low
    opens it); grip_input: the digital input bit (0-17) high while a part is held (None: no grip detection).
    tool_outputs: the outputs are the tool connector's (0-1). settle_s: the time it needs to act, s."""

    close_output: int = 0
    open_output: int | None = 1
    grip_input: int | None = None
    tool_outputs: bool = False
    settle_s: float = 0.3
    kind: str = "io"


@dataclass(frozen=True)
class VacuumDriverSpec:
    """A vacuum gripper: vacuum_output high sucks; release_output (None: none) is pulsed to blow the part off.
    The vacuum level is a digital input bit (`digital_input`, high = held) or a standard analog input
    (`analog_input` 0 or 1) compared with `threshold` (in the input's unit, V or A), held when the level is
    `held_when` ('above' or 'below') it. settle_s: time to build or release vacuum, s."""

    vacuum_output: int = 0
    release_output: int | None = None
    tool_outputs: bool = False
    digital_input: int | None = None
    analog_input: int | None = None
    threshold: float = 0.0
    held_when: str = "above"
    settle_s: float = 0.3
    kind: str = "vacuum"


GripperDriverSpec = RobotiqDriverSpec | IODriverSpec | VacuumDriverSpec


def _err(path: str, msg: str) -> CellConfigError:
    return CellConfigError(msg, path)


def _keys(d: Any, path: str, allowed: tuple[str, ...]) -> dict[str, Any]:
    if not isinstance(d, dict):
        raise _err(path, f"expected a mapping, got {type(d).__name__} {d!r:.60}")
    for key in d:
        if key not in allowed:
            close = get_close_matches(str(key), allowed, n=1, cutoff=0.75)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise _err(f"{path}.{key}", f"unknown key; {hint}allowed here: {', '.join(allowed)}")
    return d


def _int(d: dict[str, Any], key: str, path: str, lo: int, hi: int, default: int | None, what: str) -> int:
    v = d.get(key, default)
    if v is None:
        raise _err(f"{path}.{key}", "required key is missing")
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise _err(f"{path}.{key}", f"expected {what} (a whole number {lo}-{hi}), got {v!r:.60}")
    return v


def _opt_int(d: dict[str, Any], key: str, path: str, lo: int, hi: int, what: str) -> int | None:
    if d.get(key) is None:
        return None
    return _int(d, key, path, lo, hi, None, what)


def _float(d: dict[str, Any], key: str, path: str, lo: float, hi: float, default: float, unit: str) -> float:
    v = d.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v) or not lo <= float(v) <= hi:
        raise _err(f"{path}.{key}", f"expected a number in [{lo:g}, {hi:g}] {unit}, got {v!r:.60}")
    return float(v)


def _bool(d: dict[str, Any], key: str, path: str, default: bool) -> bool:
    v = d.get(key, default)
    if not isinstance(v, bool):
        raise _err(f"{path}.{key}", f"expected true or false, got {v!r:.60}")
    return v


def parse_gripper_driver(v: Any, path: str, tool_kind: str, stroke_m: float) -> GripperDriverSpec:
    """Validate a `gripper.driver` mapping for a tool of `tool_kind` ('parallel' or 'suction') and jaw stroke (m)."""
    if not isinstance(v, dict):
        raise _err(path, f"expected a mapping with a type (robotiq, io or vacuum), got {v!r:.60}")
    kind = v.get("type")
    if kind not in ("robotiq", "io", "vacuum"):
        raise _err(f"{path}.type", f"expected robotiq, io or vacuum, got {kind!r:.60}")
    if kind == "robotiq":
        d = _keys(v, path, _ROBOTIQ_KEYS)
        if tool_kind != "parallel":
            raise _err(f"{path}.type", f"a Robotiq 2F driver needs a parallel gripper, this one is {tool_kind}")
        model = str(d.get("model", "2F-85")).upper()
        if model not in ROBOTIQ_STROKES_M:
            raise _err(f"{path}.model", f"expected one of {', '.join(ROBOTIQ_STROKES_M)}, got {d.get('model')!r:.60}")
        stroke = ROBOTIQ_STROKES_M[model]
        if abs(stroke - stroke_m) > 0.002:
            raise _err(
                f"{path}.model",
                f"a Robotiq {model} opens {stroke * 1000:.0f} mm, the gripper's stroke_m is {stroke_m * 1000:.1f} mm: "
                "planned openings would not match the commanded ones",
            )
        open_c = _int(d, "open_counts", path, 0, 255, 0, "a position register value")
        closed_c = _int(d, "closed_counts", path, 0, 255, 255, "a position register value")
        if closed_c - open_c < 50:
            raise _err(
                f"{path}.closed_counts",
                f"closed_counts {closed_c} must be at least 50 above open_counts {open_c} (0 open ... 255 closed)",
            )
        return RobotiqDriverSpec(
            model=model,
            stroke_m=stroke,
            port=_int(d, "port", path, 1, 65535, 63352, "a TCP port"),
            speed=_int(d, "speed", path, 0, 255, 255, "a speed register value"),
            force=_int(d, "force", path, 0, 255, 100, "a force register value"),
            open_counts=open_c,
            closed_counts=closed_c,
            calibrate=_bool(d, "calibrate", path, False),
            activation_timeout_s=_float(d, "activation_timeout_s", path, 0.1, 60.0, 5.0, "s"),
            move_timeout_s=_float(d, "move_timeout_s", path, 0.1, 60.0, 3.0, "s"),
        )
    if kind == "io":
        d = _keys(v, path, _IO_KEYS)
        tool = _bool(d, "tool_outputs", path, False)
        n_out = _N_TOOL_OUTPUTS if tool else _N_OUTPUTS
        what = "a tool output (0-1)" if tool else "a digital output (0-7 standard, 8-15 configurable)"
        close = _int(d, "close_output", path, 0, n_out - 1, 0, what)
        opened = _opt_int(d, "open_output", path, 0, n_out - 1, what) if "open_output" in d else 1 % n_out
        if opened == close:
            raise _err(f"{path}.open_output", f"open_output and close_output are both {close}")
        return IODriverSpec(
            close_output=close,
            open_output=opened,
            grip_input=_opt_int(d, "grip_input", path, 0, _N_INPUT_BITS - 1, "a digital input bit (0-17)"),
            tool_outputs=tool,
            settle_s=_float(d, "settle_s", path, 0.0, 10.0, 0.3, "s"),
        )
    d = _keys(v, path, _VACUUM_KEYS)
    if tool_kind != "suction":
        raise _err(f"{path}.type", f"a vacuum driver needs a suction gripper, this one is {tool_kind}")
    tool = _bool(d, "tool_outputs", path, False)
    n_out = _N_TOOL_OUTPUTS if tool else _N_OUTPUTS
    what = "a tool output (0-1)" if tool else "a digital output (0-7 standard, 8-15 configurable)"
    vac = _int(d, "vacuum_output", path, 0, n_out - 1, 0, what)
    release = _opt_int(d, "release_output", path, 0, n_out - 1, what)
    if release == vac:
        raise _err(f"{path}.release_output", f"release_output and vacuum_output are both {vac}")
    lp = f"{path}.level_input"
    if "level_input" not in d:
        raise _err(lp, "required key is missing: {digital: BIT} or {analog: 0|1, threshold: LEVEL, held_when: above}")
    lv = _keys(d["level_input"], lp, _LEVEL_KEYS)
    if ("digital" in lv) == ("analog" in lv):
        raise _err(lp, "give exactly one of digital (an input bit) or analog (standard analog input 0 or 1)")
    digital = analog = None
    threshold, held_when = 0.0, "above"
    if "digital" in lv:
        extra = [k for k in ("threshold", "held_when") if k in lv]
        if extra:
            raise _err(f"{lp}.{extra[0]}", "a digital level input has no threshold: the bit is high while held")
        digital = _int(lv, "digital", lp, 0, _N_INPUT_BITS - 1, None, "a digital input bit (0-17)")
    else:
        analog = _int(lv, "analog", lp, 0, 1, None, "a standard analog input (0 or 1)")
        if "threshold" not in lv:
            raise _err(f"{lp}.threshold", "required key is missing (the level in V or A, as the input is set)")
        threshold = _float(lv, "threshold", lp, -30.0, 30.0, 0.0, "V or A")
        held_when = lv.get("held_when", "above")
        if held_when not in ("above", "below"):
            raise _err(f"{lp}.held_when", f"expected above or below, got {held_when!r:.60}")
    return VacuumDriverSpec(
        vacuum_output=vac,
        release_output=release,
        tool_outputs=tool,
        digital_input=digital,
        analog_input=analog,
        threshold=threshold,
        held_when=held_when,
        settle_s=_float(d, "settle_s", path, 0.0, 10.0, 0.3, "s"),
    )
