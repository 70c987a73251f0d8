"""The one way to get a segmenter by name, used by every command and by `pipeline`.

Kinds: 'model' (the bundled ONNX model, or the one at `model_path`), 'depth' (model-free; labels come from the
template fit), 'cad' (the library's CAD templates found in the whole region of interest, no masks:
`perception.cad_detector.CadDetector`; `pipeline.perceive` hands it the library and takes its poses as the fits),
'gt' (the data's own true masks: needs `ground_truth`, a BOP scene or a synthetic source), and 'auto' (the model when
it loads and knows every label of the library, else the depth segmenter, with a warning). 'auto' does not fall back
to 'cad': on held-out piles (benchmarks/bench_cad.py) the cad detector still accepts wrong poses (precision 0.72;
the depth segmenter's fitted segments 1.0 on the same frames) and takes seconds per frame, so it is chosen only by
name until its figures reach its targets (docs/cad_detection.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection, Iterable
from dataclasses import dataclass
from pathlib import Path

from normpos_grasp.errors import InputError, MissingDependency, NormposError, SegmentationError
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.records.template import Template

logger = logging.getLogger(__name__)

SEGMENTER_KINDS = ("model", "depth", "cad", "gt", "auto")


@dataclass(frozen=True, eq=False)
class SegmenterChoice:
    """The segmenter made and the kind it is ('model', 'depth', 'cad' or 'gt': 'auto' resolved)."""

    segmenter: Segmenter
    kind: str


def choose_segmenter(
    kind: str,
    model_path: str | Path | None = None,
    labels: Collection[str] = (),
    ground_truth: Callable[[], Segmenter] | None = None,
    library: Iterable[Template] | None = None,
) -> SegmenterChoice:
    """The segmenter of `kind` (see the module docstring). labels: the library's labels, which 'auto' needs the
    model to know. ground_truth: makes the true-mask segmenter for 'gt'. library: the templates 'cad' detects (it
    may also get them later from `pipeline.perceive`). Raises InputError for an unknown kind, SegmentationError
    when the model cannot be loaded (kind 'model')."""
    if kind == "gt":
        if ground_truth is None:
            raise InputError("the 'gt' segmenter needs data with true masks (a BOP scene or a synthetic source)")
        return SegmenterChoice(ground_truth(), "gt")
    if kind == "depth":
        from normpos_grasp.perception.depth_segmenter import DepthSegmenter

        return SegmenterChoice(DepthSegmenter(), "depth")
    if kind == "cad":
        from normpos_grasp.perception.cad_detector import CadDetector

        return SegmenterChoice(CadDetector(library), "cad")
    if kind == "model":
        return SegmenterChoice(_load_model(model_path), "model")
    if kind == "auto":
        try:
            model = _load_model(model_path)
        except (SegmentationError, MissingDependency) as exc:
            logger.warning("the segmentation model is unavailable (%s): using the depth segmenter", exc)
            return choose_segmenter("depth")
        missing = sorted(set(labels) - set(getattr(model, "class_names", ())))
        if missing:
            logger.warning("the model does not know the labels %s: using the depth segmenter", missing)
            return choose_segmenter("depth")
        return SegmenterChoice(model, "model")
    raise InputError(f"unknown segmenter {kind!r}; choose one of {', '.join(SEGMENTER_KINDS)}")


def make_segmenter(
    kind: str,
    model_path: str | Path | None = None,
    labels: Collection[str] = (),
    ground_truth: Callable[[], Segmenter] | None = None,
    library: Iterable[Template] | None = None,
) -> Segmenter:
    """`choose_segmenter(...).segmenter`."""
    return choose_segmenter(kind, model_path, labels, ground_truth, library).segmenter


def _load_model(model_path: str | Path | None) -> Segmenter:
    try:
        from normpos_grasp.perception.onnx_segmenter import OnnxSegmenter

        return OnnxSegmenter(model_path)
    except NormposError:
        raise
    except (ImportError, OSError, ValueError) as exc:
        where = f" {model_path}" if model_path is not None else ""
        raise SegmentationError(f"cannot load the segmentation model{where}: {exc}") from exc
