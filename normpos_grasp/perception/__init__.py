"""Instance segmentation: the `Segmenter` interface and its implementations (ONNX model, depth, ground truth)."""

from normpos_grasp.perception.base import Instance, Segmenter

__all__ = ["Instance", "Segmenter"]
