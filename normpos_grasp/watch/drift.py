"""The static-reference drift check in every frame, before planning (camera.static_reference, resolution method 1).

The reference points are found again in each frame by normalised cross-correlation of their stored patches, the
camera pose is re-solved (EPnP + refinement) and compared with the calibration. Pose and pixel shift are both
judged: for a plate far from the camera a small translation and a small rotation move the image alike, so the
re-solved pose splits a bump between them unreliably, while the shift of the points themselves is measured to a
few hundredths of a pixel. The camera has moved when the re-solved translation, rotation or the largest point
shift exceeds its tolerance; the error says by how much (mm, deg, px).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.camera.static_reference import (
    DriftOptions,
    DriftReport,
    StaticReference,
    check_drift,
    locate_reference_points,
)
from normpos_grasp.cell.config import WatchSpec
from normpos_grasp.errors import CameraMoved


@dataclass(frozen=True)
class DriftLimits:
    """Tolerances: translation mm, rotation deg, largest shift of a reference point px."""

    max_translation_mm: float = 1.0
    max_rotation_deg: float = 0.1
    max_shift_px: float = 0.35

    @classmethod
    def from_spec(cls, spec: WatchSpec) -> DriftLimits:
        return cls(spec.drift_max_translation_mm, spec.drift_max_rotation_deg, spec.drift_max_shift_px)


class FrameDriftCheck:
    """Checks frames against a static reference; `check` raises CameraMoved (with the report) when moved. camera:
    the intrinsics the reference was made with (None: each frame's own camera)."""

    def __init__(
        self,
        reference: StaticReference,
        camera: Camera | None,
        limits: DriftLimits | None = None,
        options: DriftOptions | None = None,
    ) -> None:
        self.reference = reference
        self.camera = camera
        self.limits = DriftLimits() if limits is None else limits
        self.options = replace(DriftOptions() if options is None else options, raise_on_drift=False)

    def measure(self, frame: RGBDFrame) -> DriftReport:
        """The drift report of `frame` (never raises for drift; CalibrationError when under 4 points are found)."""
        pixels = locate_reference_points(self.reference, frame.rgb, self.options)
        camera = self.camera if self.camera is not None else frame.camera
        return check_drift(camera, self.reference, pixels, self.options, depth_m=frame.depth_m)

    def moved(self, report: DriftReport) -> bool:
        lim = self.limits
        shift = float(np.nanmax(report.pixel_shift_px))
        return bool(
            report.translation_mm > lim.max_translation_mm
            or report.rotation_deg > lim.max_rotation_deg
            or shift > lim.max_shift_px
        )

    def check(self, frame: RGBDFrame) -> DriftReport:
        """The report of an unmoved camera; CameraMoved saying by how much otherwise."""
        report = self.measure(frame)
        if self.moved(report):
            lim = self.limits
            shift = np.nan_to_num(report.pixel_shift_px)
            worst = tuple(int(i) for i in np.nonzero(shift > lim.max_shift_px)[0])
            raise CameraMoved(
                f"camera moved since calibration: {report.translation_mm:.2f} mm, {report.rotation_deg:.3f} deg, "
                f"reference points shifted by up to {float(shift.max()):.2f} px (limits {lim.max_translation_mm:g} "
                f"mm, {lim.max_rotation_deg:g} deg, {lim.max_shift_px:g} px); points "
                f"{[self.reference.names[i] for i in worst]}. The loop stopped before planning: re-calibrate the "
                "extrinsics (`normpos-grasp calibrate extrinsics`)",
                worst,
                report,
            )
        return report
