"""The perception-to-plan chain for one frame: segment -> measure -> fit -> (plan).

One place that strings the stages together, used by the CLI commands (`plan`, `run`, `demo`, `simulate`) and by
users who call the library. Stages stay independent; this module only orders them and times them.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.measure.depth_bias import DepthBiasEstimate, DepthBiasOptions, check_frame_depth
from normpos_grasp.measure.measure import MeasureOptions, measure_instances
from normpos_grasp.measure.uncovered import UncoveredOptions, uncovered_points
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.perception.cad_detector import CadDetector, RegionOfInterest
from normpos_grasp.perception.change import unchanged
from normpos_grasp.perception.factory import ClassAgnostic, for_library, make_segmenter
from normpos_grasp.planning.plan import PlanOptions, plan_pick
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_many
from normpos_grasp.templates.select import one_pose_per_object
from normpos_grasp.typing import FloatArray

__all__ = ["FrameResult", "PipelineOptions", "ReuseOptions", "make_segmenter", "perceive", "process_frame"]


@dataclass(frozen=True)
class ReuseOptions:
    """When `perceive` keeps an accepted fit of the previous frame instead of fitting the object again: its new mask
    overlaps the old one by `min_iou` and the median depth under it (and under each half of it) changed by at most
    `max_depth_change_m` metres (`perception.change.unchanged`). Only for a camera that did not move."""

    min_iou: float = 0.95
    max_depth_change_m: float = 0.0015

    def __post_init__(self) -> None:
        if not 0.0 < self.min_iou <= 1.0 or not self.max_depth_change_m > 0.0:
            raise InputError(
                f"reuse needs min_iou in (0, 1] and max_depth_change_m > 0, got {self.min_iou}, "
                f"{self.max_depth_change_m}"
            )


@dataclass(frozen=True)
class PipelineOptions:
    """Settings of every stage; each keeps its own units (see the stage's *Options docstring).

    fit_workers: threads fitting a frame's objects (`fit_many`); 1 in processes that already run one per core.
    reuse: how `perceive(..., previous=...)` decides an object did not move.
    depth_bias: `process_frame` estimates the frame's depth bias from the cell's support plane with these settings
        and removes it (`measure.depth_bias.check_frame_depth`); None turns the check off.
    uncovered: `process_frame` hands the planner the measured surfaces in the cell's bins that no instance covers
        (`measure.uncovered.uncovered_points`: what the segmenter missed becomes an obstacle); None: only what was
        segmented is in the collision world.
    """

    measure: MeasureOptions = field(default_factory=MeasureOptions)
    fit: FitOptions = field(default_factory=FitOptions)
    plan: PlanOptions = field(default_factory=PlanOptions)
    fit_workers: int = 2
    reuse: ReuseOptions = field(default_factory=ReuseOptions)
    depth_bias: DepthBiasOptions | None = field(default_factory=DepthBiasOptions)
    uncovered: UncoveredOptions | None = field(default_factory=UncoveredOptions)


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What the pipeline made of one frame; `plan` is None when planning was not asked for.

    timings_ms: wall time per stage ('segment', 'measure', 'fit', 'plan'), milliseconds.
    reused_fits: fits kept from the previous frame (objects that did not move), the others were fitted anew.
    depth_check: the frame's depth bias estimate and warnings (`process_frame` with a support plane), else None;
        `frame` is then the corrected frame.
    """

    frame: RGBDFrame
    instances: list[Instance]
    normpositions: list[NormPosition]
    fits: list[TemplateFit]
    plan: PickPlan | None
    timings_ms: dict[str, float]
    reused_fits: int = 0
    depth_check: DepthBiasEstimate | None = None

    @property
    def accepted_fits(self) -> list[TemplateFit]:
        return [f for f in self.fits if f.accepted]


def perceive(
    frame: RGBDFrame,
    segmenter: Segmenter | None,
    library: Iterable[Template],
    options: PipelineOptions | None = None,
    instances: Sequence[Instance] | None = None,
    previous: FrameResult | None = None,
    cell: CellConfig | None = None,
) -> FrameResult:
    """Segment (unless `instances` are given), measure and fit every object of `frame`; no planning.

    previous: the last frame's result from the same, unmoved camera: an object whose mask and depth did not change
    since then keeps its accepted fit (`PipelineOptions.reuse`); everything else is fitted anew.
    A `CadDetector` segmenter (kind 'cad') detects the library's templates itself: its poses are the fits (not fitted
    again); its region of interest defaults to `cell`'s bin interior or table top.
    """
    opts = options or PipelineOptions()
    templates = list(library)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if instances is None and isinstance(segmenter, CadDetector):
        roi = RegionOfInterest.from_cell(cell) if cell is not None and segmenter.roi is None else None
        det = segmenter.detect(frame, templates, opts.measure, opts.fit, roi=roi)
        timings["segment"] = det.timings_ms.get("total", _ms(t0))
        timings["measure"] = 0.0
        timings["fit"] = 0.0  # the poses come with the detection (included in 'segment')
        return FrameResult(frame, det.instances, det.normpositions, det.fits, None, timings)
    if instances is not None:
        found = list(instances)
    elif segmenter is not None:
        # a model that lacks some of the library's labels (taught parts): its masks class-agnostic, the fit names them
        segmenter = for_library(segmenter, {t.label for t in templates})
        found = segmenter.segment(frame)
    else:
        raise InputError("perceive needs a segmenter or the frame's instances")
    timings["segment"] = _ms(t0)
    t0 = time.perf_counter()
    normpositions = measure_instances(frame, found, opts.measure)
    timings["measure"] = _ms(t0)
    t0 = time.perf_counter()
    kept = _unchanged_fits(frame, found, previous, opts.reuse) if previous is not None else {}
    todo = [n for n in normpositions if n.instance_id not in kept]
    ctx = FitContext(frame.camera, frame.depth_m)
    if instances is None and isinstance(segmenter, ClassAgnostic):
        fresh = iter(_fit_hinted(todo, templates, segmenter, opts, ctx))
    else:
        fresh = iter(fit_many(todo, templates, opts.fit, ctx, opts.fit_workers))
    fits = [kept[n.instance_id] if n.instance_id in kept else next(fresh) for n in normpositions]
    fits = one_pose_per_object(fits, normpositions)  # fragments of one object: the best-explaining fit only
    timings["fit"] = _ms(t0)
    return FrameResult(frame, found, normpositions, fits, None, timings, len(normpositions) - len(todo))


def _fit_hinted(
    todo: Sequence[NormPosition],
    templates: Sequence[Template],
    segmenter: ClassAgnostic,
    opts: PipelineOptions,
    ctx: FitContext,
) -> list[TemplateFit]:
    """Fits of class-agnostic instances, in input order: each is fitted as the model's class (its hint) and against
    the templates the model does not know (`ClassAgnostic.unknown`, label ''), or against the whole library where
    the hint is itself such a label (a weak class from a head refit); the model's class is a prior: another
    template must be accepted and explain the points clearly better (the hinted fit below `class_ambiguity_ratio`
    of its score) to overrule an accepted fit of the hinted class."""
    unknown = segmenter.unknown(templates)
    hinted = [replace(n, label=segmenter.hints.get(n.instance_id, "")) for n in todo]
    first = fit_many([n for n in hinted if n.label], templates, opts.fit, ctx, opts.fit_workers)
    by_hint = {f.instance_id: f for f in first}
    weak = {t.label for t in unknown}
    plain = [n for n in todo if segmenter.hints.get(n.instance_id, "") not in weak]
    wide = [n for n in todo if segmenter.hints.get(n.instance_id, "") in weak]  # a weak hint: the whole library
    second = fit_many(plain, unknown, opts.fit, ctx, opts.fit_workers) if unknown and plain else []
    second += fit_many(wide, templates, opts.fit, ctx, opts.fit_workers) if wide else []
    by_unknown = {f.instance_id: f for f in second}
    out = []
    for n in todo:
        h, u = by_hint.get(n.instance_id), by_unknown.get(n.instance_id)
        if h is None or u is None:
            fit = h if u is None else u
        elif h.accepted and not (u.accepted and h.score < opts.fit.class_ambiguity_ratio * u.score):
            fit = h
        elif u.accepted or u.score > h.score:
            fit = u
        else:
            fit = h
        if fit is None:  # neither a hint nor unknown templates: the whole library competes
            fit = fit_many([n], templates, opts.fit, ctx, 1)[0]
        out.append(fit)
    return out


def _unchanged_fits(
    frame: RGBDFrame, instances: Sequence[Instance], previous: FrameResult, reuse: ReuseOptions
) -> dict[int, TemplateFit]:
    """Accepted fits of `previous` for the instances of `frame` that did not move, by new instance id; each old
    fit is kept for at most one new instance."""
    old_masks = {i.instance_id: i.mask for i in previous.instances}
    old = [(old_masks[f.instance_id], f) for f in previous.fits if f.accepted and f.instance_id in old_masks]
    depth = frame.depth_m
    kept: dict[int, TemplateFit] = {}
    for inst in instances:
        for k, (old_mask, fit) in enumerate(old):
            if unchanged(inst.mask, depth, old_mask, previous.frame.depth_m, reuse.min_iou, reuse.max_depth_change_m):
                kept[inst.instance_id] = replace(fit, instance_id=inst.instance_id)
                del old[k]
                break
    return kept


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
    check = None
    if opts.depth_bias is not None:
        frame, check = check_frame_depth(frame, cell, opts.depth_bias)
    result = perceive(frame, segmenter, library, opts, instances, cell=cell)
    t0 = time.perf_counter()
    uncovered = None
    if opts.uncovered is not None:
        uncovered = uncovered_points(frame, [i.mask for i in result.instances], cell.bins, opts.uncovered)
    plan = plan_pick(result.fits, result.normpositions, cell, opts.plan, start_q, uncovered)
    timings = dict(result.timings_ms, plan=_ms(t0))
    return FrameResult(frame, result.instances, result.normpositions, result.fits, plan, timings, depth_check=check)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
