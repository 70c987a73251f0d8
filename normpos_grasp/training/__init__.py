"""Training of the bundled segmentation model (needs the optional `train` extra: torch).

`data` makes training samples from the synthetic-scene generator, `model` holds the network (imported lazily),
`trainer` trains it and exports ONNX in the YOLOv8-seg layout that `OnnxSegmenter` decodes.
"""
