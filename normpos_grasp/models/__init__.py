"""The bundled models: normpos_seg.onnx (RGB-D part segmenter, see docs/segmentation.md) and its class names."""
