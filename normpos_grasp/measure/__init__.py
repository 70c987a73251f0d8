"""Norm-position measurement: depth filling, back-projection of masks to world points, object summaries."""

from normpos_grasp.records.normpos import NormPosition, OrientedBox

__all__ = ["NormPosition", "OrientedBox"]
