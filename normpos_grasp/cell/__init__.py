"""Cell descriptions: the YAML schema, its loader and validation (`load_cell`, `CellConfig`)."""

from normpos_grasp.cell.config import (
    BinSpec,
    BoxSpec,
    CellConfig,
    MotionLimits,
    PlaceSpec,
    cell_from_dict,
    load_cell,
    parse_pose,
)

__all__ = [
    "BinSpec",
    "BoxSpec",
    "CellConfig",
    "MotionLimits",
    "PlaceSpec",
    "cell_from_dict",
    "load_cell",
    "parse_pose",
]
