"""Training pipeline end to end at toy scale: render one scene, pack, train two steps, export, decode with
OnnxSegmenter (the export must be in the layout the decoder reads)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from normpos_grasp.errors import InputError
from normpos_grasp.perception.onnx_segmenter import DepthChannelSpec, OnnxSegmenter, OnnxSegmenterOptions
from normpos_grasp.training.data import (
    CLASS_NAMES,
    cell_samples,
    frame_samples,
    pack_sample,
    pile_samples,
    read_shards,
    synth_samples,
)
from normpos_grasp.training.trainer import TrainOptions, generate_sample_shards, generate_shards, train


def test_pack_sample_boxes_and_masks_agree() -> None:
    sample = synth_samples(424242, views=1, count=4, container="table")[0]
    assert all(i.label in CLASS_NAMES for i in sample.instances)
    x, masks, boxes, classes = pack_sample(sample, (96, 128), DepthChannelSpec(), min_pixels=50)
    assert x.shape == (4, 96, 128)
    assert len(masks) == len(boxes) == len(classes) >= 1
    for m, b in zip(masks, boxes, strict=True):
        ys, xs = np.nonzero(m)
        if len(ys) == 0:
            continue
        # mask pixels (stride 4) lie inside the box, up to one mask cell
        assert xs.min() * 4 >= b[0] - 4 and (xs.max() + 1) * 4 <= b[2] + 4
        assert ys.min() * 4 >= b[1] - 4 and (ys.max() + 1) * 4 <= b[3] + 4


@pytest.mark.slow
def test_cell_and_frame_shards(tmp_path: Path) -> None:
    from normpos_grasp.cell import resolve_cell

    cell = resolve_cell("ur5e_bin_parallel")
    samples = cell_samples(cell, 5)
    assert 1 <= len(samples) <= 2
    # the demo's view: the cell's own camera; the second frame (after picks) has fewer parts
    assert np.allclose(samples[0].frame.camera.world_from_camera, cell.world_from_camera)
    if len(samples) == 2:
        assert len(samples[1].instances) <= len(samples[0].instances)
    assert all(i.label in CLASS_NAMES for s in samples for i in s.instances)
    assert all(len(s.visib_fract) == len(s.instances) for s in samples)
    generate_sample_shards(tmp_path, "frame", range(3, 4), (96, 128), frame_samples, shard_size=1)
    xs, ms, _, cs = read_shards(tmp_path)
    assert xs.shape == (1, 4, 96, 128) and len(ms[0]) == len(cs[0]) >= 1


@pytest.mark.slow
def test_pile_samples_are_reproducible_dense_piles() -> None:
    a = pile_samples(400123, views=1)
    b = pile_samples(400123, views=1)
    assert len(a) == 1 and len(a[0].instances) >= 3
    assert np.array_equal(a[0].frame.depth_m, b[0].frame.depth_m)
    assert [i.label for i in a[0].instances] == [i.label for i in b[0].instances]


def test_train_two_steps_and_decode(tmp_path: Path) -> None:
    data = tmp_path / "data"
    generate_shards(data, range(7, 8), (96, 128), views=1, shard_size=1)
    xs, _, _, _ = read_shards(data)
    assert xs.shape == (1, 4, 96, 128)
    opts = TrainOptions(input_hw=(96, 128), width=16, steps=2, batch=1, threads=1, seed=3)
    path = train(data, tmp_path / "out", opts)
    seg = OnnxSegmenter(path, options=OnnxSegmenterOptions(conf_threshold=0.0, max_detections=5))
    assert seg.class_names == list(CLASS_NAMES)
    assert seg.channels == 4 and seg.input_hw == (96, 128)
    sample = synth_samples(8, views=1, count=3, container="table")[0]
    inst = seg.segment(sample.frame)
    assert all(i.mask.shape == sample.frame.depth_m.shape and i.label in CLASS_NAMES for i in inst)
    with pytest.raises(InputError, match="depth"):
        seg.run_raw(sample.frame.rgb, None)
