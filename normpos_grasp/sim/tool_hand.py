"""The physics hand of a cell's tool (`records.tool.ToolModel`): the packaged gripper of its name, else the preset
of its kind with the tool's stroke or cup; on a dual-tool flange with the idle tool's body among its shapes."""

from __future__ import annotations

import logging
from dataclasses import replace

from normpos_grasp.errors import InputError, NormposError
from normpos_grasp.records.tool import IDLE_PREFIX, ToolModel
from normpos_grasp.sim.physics import GripperSpec, _shape_max_z

logger = logging.getLogger(__name__)

#: physics presets `--gripper` may name
PRESETS = ("2f85", "2f140", "suction")


def tool_spec(tool: ToolModel, override: str = "") -> GripperSpec:
    """The physics model of `tool` (a ToolModel) or of `override`: the packaged gripper of its name, else the
    preset of its kind with its stroke or cup; on a dual-tool flange the idle tool's body (`records.tool.with_idle`)
    is added to the hand's body shapes, so physics judges contacts of the whole end effector."""
    spec = _own_spec(tool, override)
    idle = [(s, pose) for s, pose in tool.posed_shapes(tool.min_opening_m) if s.name.startswith(IDLE_PREFIX)]
    if not idle:
        return spec
    body = list(spec.body_shapes)
    if not body:  # a preset hand: its body from the tool's own fixed shapes (the cup itself rides its bellows)
        for s, pose in tool.posed_shapes(0.0):
            if not s.name.startswith(IDLE_PREFIX) and not s.moves:
                if spec.kind == "suction" and _shape_max_z(s.kind, s.size, pose) > -spec.bellows_travel_m - 1e-3:
                    continue
                body.append((s.kind, tuple(float(v) for v in s.size), pose))
    body.extend((s.kind, tuple(float(v) for v in s.size), pose) for s, pose in idle)
    return replace(spec, body_shapes=tuple(body))


def _own_spec(tool: ToolModel, override: str) -> GripperSpec:
    from normpos_grasp.kinematics.gripper import Gripper

    name = override or tool.name
    try:
        return GripperSpec.from_gripper(Gripper.load(name))
    except NormposError as exc:  # the cell's own tool may be unpackaged: the preset of its kind stands in
        if override and override not in PRESETS:
            raise InputError(
                f"unknown gripper {override!r} for --gripper: give a packaged gripper or one of "
                f"{', '.join(PRESETS)} ({exc})"
            ) from exc
        logger.debug("gripper %r not packaged (%s); using the %s preset", name, exc, tool.kind)
    if name in PRESETS:
        return GripperSpec.preset(name)
    spec = GripperSpec.preset("suction" if tool.kind == "suction" else "2f85")
    if tool.kind == "parallel" and tool.stroke_m > 0:
        spec = replace(spec, stroke_m=float(tool.stroke_m))
    if tool.kind == "suction" and tool.cup_diameter_m > 0:
        spec = replace(spec, cup_diameter_m=float(tool.cup_diameter_m))  # the cell's own cup, not the preset's
    return spec
