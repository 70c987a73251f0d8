"""`Instance`: one segmented object (mask, label, score), what every `Segmenter` returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from normpos_grasp.errors import InputError
from normpos_grasp.typing import BoolArray


@dataclass(frozen=True, eq=False)
class Instance:
    """One segmented object.

    Attributes:
        mask: (H, W) bool, True on the object's visible pixels.
        label: class name ('' when unknown, for example from a model-free segmenter).
        score: confidence in [0, 1].
        instance_id: 1-based id, unique within a frame (0 is background in instance images).
        source_id: id in the source (for example the BOP obj_id or GT index), -1 when none.
    """

    mask: BoolArray
    label: str
    score: float
    instance_id: int = 1
    source_id: int = -1

    def __post_init__(self) -> None:
        if self.mask.ndim != 2 or self.mask.dtype != np.bool_:
            raise InputError(f"mask must be a 2-D bool array, got {self.mask.dtype} {self.mask.shape}")
        if not 0.0 <= float(self.score) <= 1.0:
            raise InputError(f"score must lie in [0, 1], got {self.score}")

    @property
    def pixel_count(self) -> int:
        return int(self.mask.sum())
