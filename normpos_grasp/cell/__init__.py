"""Cell descriptions: the YAML schema, its loader and validation (`load_cell`, `CellConfig`)."""

from normpos_grasp.cell.config import (
    BUILTIN_CELLS,
    BinSpec,
    BoxSpec,
    CellConfig,
    MotionLimits,
    PlaceSpec,
    cell_from_dict,
    load_cell,
    parse_pose,
    resolve_cell,
)

__all__ = [
    "BUILTIN_CELLS",
    "BinSpec",
    "BoxSpec",
    "CellConfig",
    "MotionLimits",
    "PlaceSpec",
    "cell_from_dict",
    "load_cell",
    "parse_pose",
    "resolve_cell",
]
