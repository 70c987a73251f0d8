"""The one way to get a segmenter by name, used by every command and by `pipeline`.

Kinds: 'model' (the bundled ONNX model, or the one at `model_path`), 'depth' (model-free; labels come from the
template fit), 'cad' (the library's CAD templates found in the whole region of interest, no masks:
`perception.cad_detector.CadDetector`; `pipeline.perceive` hands it the library and takes its poses as the fits),
'gt' (the data's own true masks: needs `ground_truth`, a BOP scene or a synthetic source), and 'auto' (the model when
it loads and knows every label of the library, else the depth segmenter, with a warning). 'auto' does not fall back
to 'cad': on held-out piles (benchmarks/bench_cad.py) the cad detector still accepts wrong poses (precision 0.72;
the depth segmenter's fitted segments 1.0 on the same frames) and takes seconds per frame, so it is chosen only by
name until its figures reach its targets (docs/cad_detection.md).

Parts the model was not trained on (a library with labels the model lacks, such as parts made with `teach`): the
model's masks are used class-agnostically (`ClassAgnostic`, from `for_library`): each instance's label becomes ''
(the model's class stays as a hint), so the templates the model does not know compete for every mask beside the
hinted class (`pipeline.perceive`: the hint is a prior, an unknown template must be accepted and clearly better to
overrule it); the verified fit names the part, and a second unknown template that explains it about as well makes
the fit ambiguous (rejected). No retraining for a new part (docs/segmentation.md says why this was chosen over a
fine-tune). 'auto' still takes the depth segmenter for such a library: on bench_teach's bins its masks of taught
parts are better.

A library folder may hold the segmenter taught its parts (`teach --segmenter-budget-min`, `train-segmenter --library
DIR --out DIR/segmenter`): DIR/segmenter/normpos_seg.onnx with its MODEL_CARD.md. `library_model` finds it, and every
command given `--library DIR` uses it for 'model' and 'auto' unless `--seg-model` names another model.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.errors import InputError, MissingDependency, NormposError, SegmentationError
from normpos_grasp.perception.base import Instance, Segmenter
from normpos_grasp.records.template import Template

logger = logging.getLogger(__name__)

SEGMENTER_KINDS = ("model", "depth", "cad", "gt", "auto")
#: where a part library keeps the segmenter taught its parts: LIBRARY/segmenter/normpos_seg.onnx (+ MODEL_CARD.md)
LIBRARY_SEGMENTER_DIR = "segmenter"
LIBRARY_MODEL_FILE = "normpos_seg.onnx"


def library_model(paths: Iterable[str | Path]) -> Path | None:
    """The segmentation model stored with the part libraries `paths` (LIBRARY/segmenter/normpos_seg.onnx), or None
    when none holds one ('builtin' and BOP folders hold none). Where several do, the first is used (logged): a
    model taught one library does not know the parts of the others, which then compete for every mask
    (`for_library`)."""
    found = [m for p in paths if str(p) != "builtin" for m in [Path(p) / LIBRARY_SEGMENTER_DIR / LIBRARY_MODEL_FILE]
             if m.is_file()]  # fmt: skip
    if len(found) > 1:
        logger.warning("several libraries hold a segmenter: using %s, not %s", found[0], [str(m) for m in found[1:]])
    if found:
        logger.info("using the library's segmenter %s", found[0])
    return found[0] if found else None


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
    may also get them later from `pipeline.perceive`). A model that lacks some of `labels` is returned
    class-agnostic (`for_library`). Raises InputError for an unknown kind, SegmentationError when the model cannot
    be loaded (kind 'model')."""
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
        return SegmenterChoice(for_library(_load_model(model_path), labels), "model")
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
        return SegmenterChoice(for_library(model, labels), "model")
    raise InputError(f"unknown segmenter {kind!r}; choose one of {', '.join(SEGMENTER_KINDS)}")


class ClassAgnostic:
    """A model's masks with the class left to the template fit: `segment` returns the model's instances with label
    '' and the model's class name in `hints` (instance_id -> name; `source_id` keeps the class index).

    For libraries with parts the model was not trained on: the bundled model masks an unknown part (it learned what
    a part is on depth and colour, though it often merges touching unknown parts) but names it with one of its own
    classes (a T-profile 'plate'), which would hand the fit only the wrong templates."""

    def __init__(self, model: Segmenter) -> None:
        self.model = model
        self.class_names: tuple[str, ...] = ()  # knows no label: `for_library` never wraps it twice
        self.hints: dict[int, str] = {}

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        found = self.model.segment(frame)
        self.hints = {i.instance_id: i.label for i in found}
        return [replace(i, label="") for i in found]

    def unknown(self, templates: Sequence[Template]) -> list[Template]:
        """The templates whose label the model lacks (taught parts) or knows only weakly (`weak_labels`, classes a
        head refit taught it, `training.head_tune`): they compete for every mask."""
        known = set(getattr(self.model, "class_names", ())) - set(getattr(self.model, "weak_labels", ()))
        return [t for t in templates if t.label not in known]


def for_library(segmenter: Segmenter, labels: Collection[str]) -> Segmenter:
    """`segmenter` as it should run for a library with `labels`: a model (a segmenter with `class_names`) that lacks
    some of them, or has `weak_labels`, becomes `ClassAgnostic`; anything else (and a model that knows every label
    surely) is returned as it is."""
    names = getattr(segmenter, "class_names", None)
    if names is None or isinstance(segmenter, ClassAgnostic):
        return segmenter
    missing = sorted((set(labels) - set(names) - {""}) | set(getattr(segmenter, "weak_labels", ())))
    if not missing:
        return segmenter
    logger.info("the model does not know the labels %s: its masks are used class-agnostically", missing)
    return ClassAgnostic(segmenter)


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
