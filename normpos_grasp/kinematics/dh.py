"""Denavit-Hartenberg chains (standard/distal DH) and UR factory-calibration corrections.

A `DHChain` is the nominal UR table plus optional per-joint corrections, the form the controller's
`calibration.conf` stores (delta_theta, delta_a, delta_d, delta_alpha): link i is
Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i). Metres and radians.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from normpos_grasp.errors import RobotModelError
from normpos_grasp.kinematics.ur_params import DH_ALPHA, URParams
from normpos_grasp.typing import ArrayLike, FloatArray

Vec6 = tuple[float, float, float, float, float, float]
_ZERO6: Vec6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class DHCalibration:
    """Per-joint DH corrections of one calibrated arm, added to the nominal table (metres, radians)."""

    delta_theta: Vec6 = _ZERO6
    delta_a: Vec6 = _ZERO6
    delta_d: Vec6 = _ZERO6
    delta_alpha: Vec6 = _ZERO6

    @staticmethod
    def from_conf(path: str | Path) -> DHCalibration:
        """Read a UR `calibration.conf`-style file: lines `delta_theta = [t1, ..., t6]` (likewise delta_a,
        delta_d, delta_alpha), any section headers and other keys ignored; missing keys default to zeros."""
        text = Path(path).read_text(encoding="utf-8")
        return DHCalibration.from_text(text, source=str(path))

    @staticmethod
    def from_text(text: str, source: str = "<text>") -> DHCalibration:
        """Parse the `calibration.conf` content `text` (see `from_conf`)."""
        values: dict[str, Vec6] = {}
        for key in ("delta_theta", "delta_a", "delta_d", "delta_alpha"):
            match = re.search(rf"^\s*{key}\s*[=:]\s*\[([^\]]*)\]", text, flags=re.MULTILINE)
            if match is None:
                continue
            try:
                numbers = [float(v) for v in match.group(1).replace(",", " ").split()]
            except ValueError as exc:
                raise RobotModelError(f"{source}: {key} must be a list of 6 numbers, got [{match.group(1)}]") from exc
            if len(numbers) != 6 or not all(math.isfinite(v) for v in numbers):
                raise RobotModelError(f"{source}: {key} must hold 6 finite numbers, got {len(numbers)}: {numbers}")
            values[key] = tuple(numbers)  # type: ignore[assignment]
        if not values:
            raise RobotModelError(
                f"{source}: no delta_theta/delta_a/delta_d/delta_alpha lists found; expected lines like "
                "'delta_theta = [0, 0, 0, 0, 0, 0]' as in a UR controller's calibration.conf"
            )
        return DHCalibration(**values)

    def to_text(self) -> str:
        """The corrections in `calibration.conf` syntax (a `[mounting]` section with four lists)."""
        lines = ["[mounting]"]
        for key in ("delta_theta", "delta_a", "delta_d", "delta_alpha"):
            lines.append(f"{key} = [" + ", ".join(repr(float(v)) for v in getattr(self, key)) + "]")
        return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class DHChain:
    """Six DH links: theta offsets, a, d, alpha, each (6,) (metres, radians)."""

    theta: Vec6
    a: Vec6
    d: Vec6
    alpha: Vec6

    @staticmethod
    def nominal(params: URParams, calibration: DHCalibration | None = None) -> DHChain:
        """The chain of a UR model, with factory corrections added when given."""
        cal = calibration or DHCalibration()

        def add(x: ArrayLike, dx: ArrayLike) -> Vec6:
            return tuple(float(v) for v in np.add(x, dx))  # type: ignore[return-value]

        return DHChain(
            add(_ZERO6, cal.delta_theta),
            add(params.a, cal.delta_a),
            add(params.d, cal.delta_d),
            add(DH_ALPHA, cal.delta_alpha),
        )

    def link_transform(self, i: int, q: float = 0.0) -> FloatArray:
        """(4, 4) transform of link i (0-based) at joint angle q: Rz(q + theta) Tz(d) Tx(a) Rx(alpha)."""
        ct, st = math.cos(q + self.theta[i]), math.sin(q + self.theta[i])
        ca, sa = math.cos(self.alpha[i]), math.sin(self.alpha[i])
        a, d = self.a[i], self.d[i]
        return np.array(
            [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]
        )

    def forward_kinematics(self, q: ArrayLike) -> FloatArray:
        """base_from_flange (..., 4, 4) for joint angles q (..., 6), radians (vectorised)."""
        qs = np.asarray(q, dtype=np.float64)
        pose = np.broadcast_to(np.eye(4), qs.shape[:-1] + (4, 4)).copy()
        for i in range(6):
            ct, st = np.cos(qs[..., i] + self.theta[i]), np.sin(qs[..., i] + self.theta[i])
            ca, sa = math.cos(self.alpha[i]), math.sin(self.alpha[i])
            link = np.zeros(qs.shape[:-1] + (4, 4))
            link[..., 0, 0] = ct
            link[..., 0, 1] = -st * ca
            link[..., 0, 2] = st * sa
            link[..., 0, 3] = self.a[i] * ct
            link[..., 1, 0] = st
            link[..., 1, 1] = ct * ca
            link[..., 1, 2] = -ct * sa
            link[..., 1, 3] = self.a[i] * st
            link[..., 2, 1] = sa
            link[..., 2, 2] = ca
            link[..., 2, 3] = self.d[i]
            link[..., 3, 3] = 1.0
            pose = pose @ link
        return pose
