"""Exception tree: every failure the library raises derives from `NormposError`.

Messages say what was expected, what came and what to do; errors carry the data needed to debug.
"""

from __future__ import annotations

from typing import Any


class NormposError(Exception):
    """Root of every error raised by normpos_grasp."""


class InputError(NormposError, ValueError):
    """An argument has the wrong shape, type, unit or value."""


class MissingDependency(NormposError, ImportError):
    """An optional package is needed for this feature; the message names the extra to install."""

    def __init__(self, package: str, extra: str, feature: str) -> None:
        super().__init__(
            f"{feature} needs the optional package '{package}': install it with `pip install 'normpos-grasp[{extra}]'`"
        )
        self.package = package
        self.extra = extra


class CalibrationError(NormposError):
    """Camera calibration failed or its input is degenerate; `indices` names the offending points."""

    def __init__(self, message: str, indices: tuple[int, ...] = ()) -> None:
        super().__init__(message)
        self.indices = indices


class CameraMoved(CalibrationError):
    """The static-reference check found the camera drifted beyond tolerance; `report` holds the drift report."""

    def __init__(self, message: str, indices: tuple[int, ...] = (), report: Any = None) -> None:
        super().__init__(message, indices)
        self.report = report


class ExtrinsicsError(InputError):
    """Camera extrinsics that cannot be right (rotation not orthonormal, a reflection, a camera under the floor or
    implausibly far away); `measured` holds the offending figure (deviation, determinant, height or distance)."""

    def __init__(self, message: str, measured: float | None = None) -> None:
        super().__init__(message)
        self.measured = measured


class DatasetError(NormposError):
    """A dataset folder (BOP or otherwise) is missing files or holds malformed data."""


class SegmentationError(NormposError):
    """A segmenter could not run on the given frame or model."""


class ModelFormatError(SegmentationError):
    """An ONNX model lacks the expected inputs/outputs or metadata."""


class MeasurementError(NormposError):
    """A norm-position could not be measured (empty mask, no valid depth)."""


class TemplateError(NormposError):
    """A CAD template or template library is invalid."""


class MeshError(TemplateError):
    """A mesh is broken beyond repair (not watertight, degenerate, wrong units)."""


class FitRejected(NormposError):
    """A template fit was rejected; `fit` holds the rejected result and its reason."""

    def __init__(self, message: str, fit: Any = None) -> None:
        super().__init__(message)
        self.fit = fit


class RobotModelError(NormposError):
    """A robot or gripper description is missing or invalid."""


class NoIKSolution(NormposError):
    """No inverse-kinematics solution; `reason` is one of out_of_reach, wrist_singularity,
    joint_limits, not_converged."""

    def __init__(self, message: str, reason: str, target: Any = None) -> None:
        super().__init__(message)
        self.reason = reason
        self.target = target


class FrameError(InputError):
    """A pose or point set used in a frame it is not in (a camera-frame fit where a world pose is needed)."""


class CellConfigError(NormposError):
    """A cell description (YAML) is invalid; `path` locates the bad key."""

    def __init__(self, message: str, path: str = "") -> None:
        super().__init__(f"{path}: {message}" if path else message)
        self.path = path


class PlanningError(NormposError):
    """Motion planning failed (no collision-free path, time-parameterisation failure)."""


class SafetyViolation(NormposError):
    """A command would leave the robot's or the cell's limits; nothing was sent."""

    def __init__(self, message: str, detail: Any = None) -> None:
        super().__init__(message)
        self.detail = detail


class DriverFault(NormposError):
    """The arm driver failed; no further motion is sent until an explicit resume."""


class ProtectiveStop(DriverFault):
    """The controller reported a protective stop."""


class EmergencyStop(DriverFault):
    """The controller reported an emergency stop."""


class ConnectionLost(DriverFault):
    """The connection to the controller dropped or stalled."""


class DriverTimeout(DriverFault):
    """The controller did not answer in time."""


class GripperFault(DriverFault):
    """The gripper failed: its socket is missing (no URCap) or dropped, it did not activate or finish a move in
    time, or it reports a fault code; `detail` holds what it last reported."""

    def __init__(self, message: str, detail: Any = None) -> None:
        super().__init__(message)
        self.detail = detail


class ZoneIntrusion(DriverFault):
    """The zone watch (normpos_grasp.watch) saw something new inside a watched volume and stopped the arm; `detail`
    holds the intrusion (zone, blob size, when the frame was taken and when the stop was sent)."""

    def __init__(self, message: str, detail: Any = None) -> None:
        super().__init__(message)
        self.detail = detail


class ControllerMismatch(NormposError):
    """The controller is not the arm the plan or cell names (robot model or serial number); nothing was sent."""


class TerminationRequested(KeyboardInterrupt):
    """SIGTERM arrived. Raised in the main thread like Ctrl-C (it is a KeyboardInterrupt, not a failure), so every
    way out of a motion stops the arm first; the CLI exits with 143 for it and 130 for SIGINT."""


class SimulationError(NormposError):
    """A scene could not be generated, rendered or simulated."""
