"""PNG bar charts of a batch (drawn with OpenCV, no plotting library): success by part, by depth, by occlusion.

Each bar is a group's success rate (0..1) with its pick count written above it; files are deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from normpos_grasp.simulate.episode import PickRecord
from normpos_grasp.typing import UInt8Array

_W, _H = 720, 420
_MARGIN = (70, 30, 40, 80)  # left, right, top, bottom, pixels


def bar_chart(title: str, labels: Sequence[str], rates: Sequence[float], counts: Sequence[int]) -> UInt8Array:
    """(H, W, 3) BGR image of a success-rate bar chart."""
    import cv2

    img = np.full((_H, _W, 3), 255, dtype=np.uint8)
    left, right, top, bottom = _MARGIN
    x0, x1, y0, y1 = left, _W - right, top, _H - bottom
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(img, title, (left, 24), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    for k in range(6):
        frac = k / 5
        y = int(round(y1 - frac * (y1 - y0)))
        cv2.line(img, (x0, y), (x1, y), (225, 225, 225), 1)
        cv2.putText(img, f"{frac:.1f}", (x0 - 40, y + 5), font, 0.45, (60, 60, 60), 1, cv2.LINE_AA)
    cv2.line(img, (x0, y0), (x0, y1), (0, 0, 0), 1)
    cv2.line(img, (x0, y1), (x1, y1), (0, 0, 0), 1)
    n = max(len(labels), 1)
    slot = (x1 - x0) / n
    for i, (label, rate, count) in enumerate(zip(labels, rates, counts, strict=True)):
        bx0 = int(round(x0 + i * slot + 0.15 * slot))
        bx1 = int(round(x0 + (i + 1) * slot - 0.15 * slot))
        if count > 0:
            by = int(round(y1 - rate * (y1 - y0)))
            colour = (80, 170, 60) if rate >= 0.98 else ((40, 160, 230) if rate >= 0.8 else (60, 60, 210))
            cv2.rectangle(img, (bx0, by), (bx1, y1), colour, -1)
            cv2.putText(img, f"n={count}", (bx0, max(by - 6, top + 10)), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        text = str(label)[:12]
        cv2.putText(img, text, (bx0, y1 + 18), font, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "success rate", (4, top - 8), font, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    return img


def _grouped(picks: Sequence[PickRecord], keys: Sequence[str], key_of: object) -> tuple[list[float], list[int]]:
    rates, counts = [], []
    for key in keys:
        group = [p for p in picks if key_of(p) == key]  # type: ignore[operator]
        counts.append(len(group))
        rates.append(sum(p.success for p in group) / len(group) if group else 0.0)
    return rates, counts


def _bin_label(value: float, edges: Sequence[float], unit: str, scale: float) -> str:
    if not np.isfinite(value):
        return "n/a"
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        if lo <= value < hi:
            return f"{lo * scale:g}-{hi * scale:g}{unit}" if np.isfinite(hi) else f">={lo * scale:g}{unit}"
    return f"<{edges[0] * scale:g}{unit}"


def write_plots(picks: Sequence[PickRecord], out_dir: str | Path) -> list[Path]:
    """Write success_by_part.png, success_by_depth.png and success_by_occlusion.png; returns their paths."""
    import cv2

    out = Path(out_dir)
    made = []
    parts = sorted({p.part or "(none)" for p in picks})
    rates, counts = _grouped(picks, parts, lambda p: p.part or "(none)")
    charts = [("success_by_part.png", "Success by part", parts, rates, counts)]
    depth_edges = [0.0, 0.02, 0.04, 0.06, 0.1, float("inf")]
    depth_keys = [_bin_label(a, depth_edges, "cm", 100) for a in depth_edges[:-1]]
    rates, counts = _grouped(picks, depth_keys, lambda p: _bin_label(p.depth_m, depth_edges, "cm", 100))
    charts.append(("success_by_depth.png", "Success by height above the bin floor", depth_keys, rates, counts))
    occ_edges = [0.0, 0.1, 0.3, 0.5, 0.7, float("inf")]
    occ_keys = [_bin_label(a, occ_edges, "%", 100) for a in occ_edges[:-1]]
    rates, counts = _grouped(picks, occ_keys, lambda p: _bin_label(p.occlusion, occ_edges, "%", 100))
    charts.append(
        ("success_by_occlusion.png", "Success by occlusion (hidden share of the part)", occ_keys, rates, counts)
    )
    for name, title, labels, r, c in charts:
        path = out / name
        cv2.imwrite(str(path), bar_chart(title, labels, r, c))
        made.append(path)
    return made
