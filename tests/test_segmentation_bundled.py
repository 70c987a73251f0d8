"""The bundled RGB-D model end to end on a rendered scene, with and without the full-resolution mask refinement."""

from __future__ import annotations

from dataclasses import replace

import mujoco  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import onnxruntime  # noqa: F401  (a hard dependency: imported, never skipped)
import pytest

from normpos_grasp.perception.onnx_segmenter import OnnxSegmenter
from normpos_grasp.training.data import synth_samples
from normpos_grasp.training.metrics import MatchStats


@pytest.fixture(scope="module")
def sample():  # type: ignore[no-untyped-def]
    # separated parts on one layer, a seed outside the training (100000+, 200000+, 300000+, 400000+) and
    # benchmark (900000+) ranges
    return synth_samples(987654, views=1, clutter=0.0, stack_layers=1, count=6)[0]


def test_refined_masks_are_disjoint_and_better_than_the_upsampled_ones(sample) -> None:  # type: ignore[no-untyped-def]
    refined = OnnxSegmenter()
    assert refined.channels == 4 and refined.options.refine_masks
    plain = OnnxSegmenter(options=replace(refined.options, refine_masks=False))
    inst = refined.segment(sample.frame)
    assert inst, "the bundled model found nothing on a scene of six separated parts"
    masks = np.array([i.mask for i in inst])
    assert masks.sum(0).max() <= 1  # one instance per pixel
    stats_r, stats_p = MatchStats(), MatchStats()
    stats_r.add(inst, sample.instances, sample.visib_fract)
    stats_p.add(plain.segment(sample.frame), sample.instances, sample.visib_fract)
    assert stats_r.recall >= 0.8
    assert stats_r.mean_iou > stats_p.mean_iou


def test_refinement_off_gives_the_decoder_masks(sample) -> None:  # type: ignore[no-untyped-def]
    base = OnnxSegmenter()
    plain = OnnxSegmenter(options=replace(base.options, refine_masks=False))
    det = plain.detect(sample.frame.rgb, sample.frame.depth_m)
    assert det.soft == ()
    inst = plain.segment(sample.frame)
    kept = [k for k in range(len(det.scores)) if det.masks[k].any()]
    assert len(inst) == len(kept)
    for i, k in zip(inst, kept, strict=True):
        assert (i.mask == det.masks[k]).all()
