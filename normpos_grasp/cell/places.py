"""Place patterns of the cell YAML (`place[i].pattern`): a grid of slots, stacked in layers, from one place pose.

`pattern: {columns: NX, rows: NY, pitch_m: [DX, DY], layers: NZ, layer_height_m: DZ}` turns the place pose into
NX * NY * NZ slots: slot (c, r, l) is the pose moved by c * DX along the pose's own x axis, r * DY along its own y
axis (horizontal for a downward-pointing TCP) and l * DZ up the world z axis. Slots are filled layer by layer, row by
row, column by column, so a layer is complete before the next one starts on top of it. Errors are CellConfigErrors
naming the key.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from normpos_grasp.errors import CellConfigError
from normpos_grasp.typing import FloatArray

PATTERN_KEYS = ("columns", "rows", "pitch_m", "layers", "layer_height_m")
MAX_SLOTS = 1000


def _count(d: dict[str, Any], key: str, path: str) -> int:
    v = d.get(key, 1)
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 100:
        raise CellConfigError(f"expected a whole number 1-100, got {v!r:.60}", f"{path}.{key}")
    return v


def _metres(v: Any, path: str, lo: float, hi: float) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v) or not lo <= float(v) <= hi:
        raise CellConfigError(f"expected a length in [{lo:g}, {hi:g}] m, got {v!r:.60}", path)
    return float(v)


def pattern_slots(pattern: Any, path: str, world_from_tcp: FloatArray, name: str) -> list[tuple[str, FloatArray]]:
    """(slot name, world_from_tcp (4, 4)) of every slot of `pattern` around the place pose, in filling order."""
    if not isinstance(pattern, dict):
        raise CellConfigError(f"expected a mapping with {', '.join(PATTERN_KEYS)}, got {pattern!r:.60}", path)
    for key in pattern:
        if key not in PATTERN_KEYS:
            raise CellConfigError(f"unknown key; allowed here: {', '.join(PATTERN_KEYS)}", f"{path}.{key}")
    nx, ny, nz = (_count(pattern, k, path) for k in ("columns", "rows", "layers"))
    if nx * ny * nz > MAX_SLOTS:
        raise CellConfigError(f"{nx * ny * nz} slots is more than {MAX_SLOTS}", path)
    pitch = pattern.get("pitch_m", [0.0, 0.0])
    if not isinstance(pitch, list) or len(pitch) != 2:
        raise CellConfigError(f"expected [DX, DY] in metres, got {pitch!r:.60}", f"{path}.pitch_m")
    dx, dy = (_metres(v, f"{path}.pitch_m[{i}]", 0.0, 5.0) for i, v in enumerate(pitch))
    if (nx > 1 and dx < 1e-3) or (ny > 1 and dy < 1e-3):
        raise CellConfigError("several columns (rows) need a pitch of at least 1 mm along x (y)", f"{path}.pitch_m")
    dz = _metres(pattern.get("layer_height_m", 0.0), f"{path}.layer_height_m", 0.0, 2.0)
    if nz > 1 and dz < 1e-3:
        raise CellConfigError("several layers need a layer_height_m of at least 1 mm", f"{path}.layer_height_m")
    x_axis, y_axis = world_from_tcp[:3, 0], world_from_tcp[:3, 1]
    out = []
    for layer in range(nz):
        for row in range(ny):
            for col in range(nx):
                pose = world_from_tcp.copy()
                pose[:3, 3] += col * dx * x_axis + row * dy * y_axis + np.array([0.0, 0.0, layer * dz])
                out.append((f"{name}[{col},{row},{layer}]", pose))
    return out
