"""The perception-to-plan chain for one frame: segment -> measure -> fit -> (plan).

One place that strings the stages together, used by the CLI commands (`plan`, `run`, `demo`, `simulate`) and by
users who call the library. Stages stay independent; this module only orders them and times them.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.measure.measure import MeasureOptions, measure_instances
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.planning.plan import PlanOptions, plan_pick
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_many
from normpos_grasp.typing import FloatArray

SEGMENTER_KINDS = ("model", "depth")


@dataclass(frozen=True)
class PipelineOptions:
    """Settings of every stage; each keeps its own units (see the stage's *Options docstring)."""

    measure: MeasureOptions = field(default_factory=MeasureOptions)
    fit: FitOptions = field(default_factory=FitOptions)
    plan: PlanOptions = field(default_factory=PlanOptions)


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What the pipeline made of one frame; `plan` is None when planning was not asked for.

    timings_ms: wall time per stage ('segment', 'measure', 'fit', 'plan'), milliseconds.
    """

    frame: RGBDFrame
    instances: list[Instance]
    normpositions: list[NormPosition]
    fits: list[TemplateFit]
    plan: PickPlan | None
    timings_ms: dict[str, float]

    @property
    def accepted_fits(self) -> list[TemplateFit]:
        return [f for f in self.fits if f.accepted]


def make_segmenter(kind: str) -> Segmenter:
    """A segmenter by name: 'model' (the bundled ONNX model) or 'depth' (model-free, labels from fitting)."""
    if kind == "model":
        from normpos_grasp.perception.onnx_segmenter import OnnxSegmenter

        return OnnxSegmenter()
    if kind == "depth":
        from normpos_grasp.perception.depth_segmenter import DepthSegmenter

        return DepthSegmenter()
    raise InputError(f"unknown segmenter {kind!r}; choose one of {', '.join(SEGMENTER_KINDS)} (or 'gt' for BOP data)")


def perceive(
    frame: RGBDFrame,
    segmenter: Segmenter,
    library: Iterable[Template],
    options: PipelineOptions | None = None,
    instances: Sequence[Instance] | None = None,
) -> FrameResult:
    """Segment (unless `instances` are given), measure and fit every object of `frame`; no planning."""
    opts = options or PipelineOptions()
    templates = list(library)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    found = list(instances) if instances is not None else segmenter.segment(frame)
    timings["segment"] = _ms(t0)
    t0 = time.perf_counter()
    normpositions = measure_instances(frame, found, opts.measure)
    timings["measure"] = _ms(t0)
    t0 = time.perf_counter()
    context = FitContext(frame.camera, frame.depth_m)
    fits = fit_many(normpositions, templates, opts.fit, context)
    timings["fit"] = _ms(t0)
    return FrameResult(frame, found, normpositions, fits, None, timings)


def process_frame(
    frame: RGBDFrame,
    segmenter: Segmenter,
    library: Iterable[Template],
    cell: CellConfig,
    options: PipelineOptions | None = None,
    start_q: FloatArray | None = None,
    instances: Sequence[Instance] | None = None,
) -> FrameResult:
    """`perceive`, then plan a pick in `cell` from `start_q` (default: the cell's home). Needs world extrinsics."""
    if frame.camera.world_from_camera is None:
        raise InputError("planning needs a camera with world_from_camera; calibrate extrinsics first")
    opts = options or PipelineOptions()
    result = perceive(frame, segmenter, library, opts, instances)
    t0 = time.perf_counter()
    plan = plan_pick(result.fits, result.normpositions, cell, opts.plan, start_q)
    timings = dict(result.timings_ms, plan=_ms(t0))
    return FrameResult(frame, result.instances, result.normpositions, result.fits, plan, timings)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
