"""The `Segmenter` interface: an RGB-D frame in, a list of object instances (mask, label, score) out."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.records.instance import Instance

__all__ = ["Instance", "Segmenter"]


@runtime_checkable
class Segmenter(Protocol):
    """Anything that turns a frame into instances. Implementations must not modify the frame."""

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        """Return the frame's object instances, instance_id 1..N, masks matching the frame's size."""
        ...
