"""Instance segmentation: the `Segmenter` interface and its implementations (ONNX model, depth, ground truth)."""

from normpos_grasp.perception.base import Segmenter
from normpos_grasp.records.instance import Instance

__all__ = ["Instance", "Segmenter"]
