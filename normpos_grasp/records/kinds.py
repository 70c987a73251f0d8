"""The closed sets of names the records use, as `Literal` types (mypy checks every assignment); FRAMES holds the
values for validation at the boundary."""

from __future__ import annotations

from typing import Literal, get_args

Frame = Literal["world", "camera"]
PlanStatus = Literal["ok", "no_feasible_grasp"]

FRAMES: tuple[Frame, ...] = get_args(Frame)
