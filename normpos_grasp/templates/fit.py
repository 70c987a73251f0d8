"""Pose fitting of CAD templates to measured norm-positions: hypotheses, trimmed ICP, scoring, acceptance.

Pipeline per (norm-position, template):
1. subsample the measured points (seeded), per-point inlier distances from the depth-noise model;
2. global hypotheses: PCA/OBB alignment in all 24 axis assignments, FPFH-matched 3-point RANSAC, and the
   template's control points matched to points detected on the measurement (OBB corners, extremal points);
3. coarse batched ICP of every hypothesis on a distance grid, keep the best distinct few;
4. exact trimmed point-to-plane ICP (camera-visible model points only) with an optional size factor;
5. scoring (inliers, RMSE, visible coverage, free-space violation, and over the pose's whole visible surface the
   share explained by depth and the share lying right behind measured points it does not explain) and acceptance
   with a reason; a second, clearly different pose that explains the data about as well makes the fit ambiguous:
   rejected. One pose per physical object across a frame's fits: `templates.select.one_pose_per_object`.
"""

from __future__ import annotations

import logging
import threading
import time
import weakref
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import FitRejected, InputError, TemplateError
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.templates import kernels
from normpos_grasp.templates.control_points import control_point_hypotheses
from normpos_grasp.templates.features import fpfh, ransac_hypotheses, voxel_downsample
from normpos_grasp.templates.icp import candidates, icp
from normpos_grasp.templates.prepared import PreparedTemplate, prepare
from normpos_grasp.templates.scoring import PoseScore, consistency_neighbours, evaluate, score_bounds
from normpos_grasp.typing import FloatArray, IntArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FitOptions:
    """Settings of `fit_template` / `fit_best`.

    Attributes:
        n_fit_points: measured points used by the exact ICP (subsampled, seeded).
        n_coarse_points: points used by the coarse stage.
        n_score_points: points used for the final inlier/RMSE score.
        inlier_distance_m: smallest inlier distance, metres.
        noise_per_m2: depth noise RMS per squared range, 1/m (D435: 0.0036; the inlier distance is
            max(inlier_distance_m, 2.5 * noise_per_m2 * range^2)).
        coarse_iterations / icp_iterations: ICP iterations of the two stages; the last `exact_iterations`
            of the fine stage use exact KD-tree correspondences (the others a distance grid);
            scale_iterations: extra iterations that also fit the size factor.
        n_refine: distinct coarse hypotheses refined exactly.
        coarse_prune_after / coarse_keep / flip_keep: after `coarse_prune_after` coarse iterations only the
            best `coarse_keep` starting poses (`flip_keep` turned copies) by inlier fraction go on (0 = all).
        fine_trim: share of correspondences kept (smallest residuals) in the fine ICP; the rest is trimmed.
        n_flip_variants: turned copies of the best pose (24 axis assignments, coarse-fitted) also refined
            and scored, so a view-induced wrong basin is caught by the ambiguity test (0 disables).
        ransac_iterations: sampled triples for the FPFH RANSAC (0 disables it).
        use_pca / use_control_points: hypothesis sources.
        fit_scale: fit a size factor (kept only when it lowers the RMSE below scale_rmse_gain x the rigid
            fit's RMSE without lowering the score); scale_tolerance: its bound (0.05 = parts up to 5 % off CAD size).
        min_points: fewer measured points -> rejected ("too few points").
        min_consistency: share of points whose locally averaged residual lies within noise (a wrong
            template leaves coherent residuals).
        min_inlier_ratio, max_rmse_m (added to the median inlier distance), min_coverage (with depth image),
        min_coverage_no_depth (without), max_free_space_violation: acceptance thresholds.
        min_explained_share / max_front_share (with a depth image): of the pose's whole camera-visible surface
            (occluded and off-image parts included) at least this share must be explained by measured depth, and
            at most this share may lie right behind a measured surface it does not explain (`PoseScore`): a small
            fragment or a wrong template passed through a surface loses.
        ambiguity_ratio: a distinct pose (ADD-S > ambiguity_add_s * diameter or, for templates without a
            continuous symmetry, symmetry-aware ADD > ambiguity_add * diameter: a turned copy whose faces overlap
            the best pose's) scoring at least this share of the best makes the fit ambiguous (rejected).
        depth_bias_m: a calibrated systematic depth offset of the sensor, metres (positive: the sensor reads
            too far); measured points are moved towards the camera by it along their rays. 0 by default.
        class_ambiguity_ratio: with label '', a second template accepted with at least this share of the best
            score makes the class ambiguous (rejected).
        seed: RNG seed for subsampling and RANSAC (results are deterministic).
    """

    n_fit_points: int = 200
    n_coarse_points: int = 60
    n_score_points: int = 400
    inlier_distance_m: float = 0.003
    noise_per_m2: float = 0.0036
    coarse_iterations: int = 6
    icp_iterations: int = 12
    exact_iterations: int = 4
    scale_iterations: int = 8
    n_refine: int = 3
    coarse_prune_after: int = 2
    coarse_keep: int = 16
    flip_keep: int = 10
    n_flip_variants: int = 4
    fine_trim: float = 0.95
    scale_rmse_gain: float = 0.97
    ransac_iterations: int = 600
    use_pca: bool = True
    use_control_points: bool = True
    fit_scale: bool = True
    scale_tolerance: float = 0.05
    min_points: int = 30
    min_inlier_ratio: float = 0.75
    min_consistency: float = 0.8
    max_rmse_m: float = 0.002
    min_coverage: float = 0.8
    min_coverage_no_depth: float = 0.3
    max_free_space_violation: float = 0.08
    min_explained_share: float = 0.35
    max_front_share: float = 0.03
    ambiguity_ratio: float = 0.95
    class_ambiguity_ratio: float = 0.85
    ambiguity_add_s: float = 0.1
    ambiguity_add: float = 0.2
    depth_bias_m: float = 0.0
    seed: int = 0


@dataclass(frozen=True, eq=False)
class FitContext:
    """Optional sensor context for the free-space and coverage tests.

    camera: the frame's camera; depth_m: (H, W) metric depth (0 = no reading) of the same frame.
    The norm-position's frame must be 'camera' or the camera must carry `world_from_camera`.
    """

    camera: Camera
    depth_m: FloatArray

    def camera_from_frame(self, frame: str) -> FloatArray:
        if frame == "camera":
            return np.eye(4)
        if self.camera.world_from_camera is None:
            raise InputError(
                f"norm-position frame is '{frame}' but the camera has no world_from_camera; "
                "calibrate extrinsics or measure in the camera frame"
            )
        return invert_pose(self.camera.world_from_camera)


@dataclass(frozen=True, eq=False)
class _Candidate:
    object_from_frame: FloatArray
    scale: float
    score: PoseScore


@dataclass(frozen=True)
class _Measured:
    pts_fit: FloatArray
    nrm_fit: FloatArray
    thr_fit: FloatArray
    pts_score: FloatArray
    nrm_score: FloatArray
    thr_score: FloatArray
    viewpoint: FloatArray
    neighbours_score: IntArray
    thr_fit_median: float
    thr_score_median: float
    all_pts: FloatArray = field(repr=False)
    all_nrm: FloatArray = field(repr=False)

    @cached_property
    def tree(self) -> cKDTree:
        """KD-tree over all measured points (built on first use: only scoring without a depth image needs it)."""
        return cKDTree(self.all_pts)


def fit_template(
    normpos: NormPosition,
    template: Template,
    options: FitOptions | None = None,
    camera: FitContext | None = None,
) -> TemplateFit:
    """Fit `template` to `normpos`; always returns a `TemplateFit` (accepted=False with a reason on failure).

    `camera` (a `FitContext`) enables the occlusion-aware coverage and the free-space test on the depth image.
    The pose is `frame_from_object` in the norm-position's frame (`fit.frame`).
    """
    opts = options or FitOptions()
    t0 = time.perf_counter()
    try:
        meas = _prepare_measurement(normpos, opts)
    except _TooFew as exc:
        return _rejected(template, normpos, str(exc), t0)
    return _fit_prepared(normpos, template, meas, opts, _context(camera, opts), 0.0, t0)


def fit_template_from(
    normpos: NormPosition,
    template: Template,
    starts: FloatArray,
    options: FitOptions | None = None,
    camera: FitContext | None = None,
) -> TemplateFit:
    """`fit_template` from given starting poses instead of its own hypotheses (a detector that already found the
    object): (K, 4, 4) `frame_from_object` in the norm-position's frame. Refinement, turned variants, scoring and
    acceptance are `fit_template`'s."""
    opts = options or FitOptions()
    t0 = time.perf_counter()
    try:
        meas = _prepare_measurement(normpos, opts)
    except _TooFew as exc:
        return _rejected(template, normpos, str(exc), t0)
    starts_ofc = np.asarray(np.linalg.inv(np.asarray(starts, dtype=np.float64).reshape(-1, 4, 4)), dtype=np.float64)
    return _fit_prepared(normpos, template, meas, opts, _context(camera, opts), 0.0, t0, starts_ofc)


def _fit_prepared(
    normpos: NormPosition,
    template: Template,
    meas: _Measured,
    opts: FitOptions,
    camera: FitContext | None,
    floor: float,
    t0: float,
    starts: FloatArray | None = None,
) -> TemplateFit:
    """`fit_template` on a prepared measurement and context (`_context`); poses whose score bound is below
    `floor` are not scored; `starts` ((K, 4, 4) object_from_frame) replace the hypotheses."""
    prep = prepare(template)
    cands = _fit_candidates(prep, template, normpos, meas, opts, camera, floor, starts)
    if not cands:
        reason = "no pose hypothesis explained the measured points"
        if floor > 0:
            reason = f"dominated: no pose can score {floor:.3f} (another template explains the points better)"
        return _rejected(template, normpos, reason, t0)
    return _decide(prep, template, normpos, cands, opts, camera, t0)


def fit_template_or_raise(
    normpos: NormPosition, template: Template, options: FitOptions | None = None, camera: FitContext | None = None
) -> TemplateFit:
    """`fit_template`, raising `FitRejected` (carrying the fit) when the fit is not accepted."""
    fit = fit_template(normpos, template, options, camera)
    if not fit.accepted:
        raise FitRejected(f"template '{template.name}' rejected: {fit.reason}", fit)
    return fit


def fit_best(
    normpos: NormPosition,
    library: object,
    options: FitOptions | None = None,
    camera: FitContext | None = None,
) -> TemplateFit:
    """Fit the templates of `library` (a TemplateLibrary or a sequence of Templates) and return the best.

    With a label on the norm-position only templates of that label (or name) are tried; with label ''
    (a model-free segmenter) every template whose size is compatible competes and the best score wins.
    A label that no template carries gives a rejected fit. Two different templates accepted with nearly
    equal scores give a rejected fit ('ambiguous class').
    """
    templates = list(library)  # type: ignore[call-overload]
    if not templates:
        raise TemplateError("the template library is empty; load templates with load_library(path)")
    opts = options or FitOptions()
    t0 = time.perf_counter()
    if normpos.label:
        chosen = [t for t in templates if normpos.label in (t.label, t.name)]
        if not chosen:
            labels = sorted({t.label for t in templates})
            return _rejected(
                templates[0], normpos, f"no template for label '{normpos.label}' (library labels: {labels})", t0
            )
    else:
        chosen = [t for t in templates if _size_compatible(normpos, t, opts)]
        if not chosen:
            return _rejected(templates[0], normpos, "no template is compatible with the measured size", t0)
    try:
        meas = _prepare_measurement(normpos, opts)
    except _TooFew as exc:
        return _rejected(chosen[0], normpos, str(exc), t0)
    # likeliest template first (measured extents closest to the template's): its score sets a floor below
    # which the other templates' poses need not be scored (they could be neither the best nor a class rival)
    chosen.sort(key=lambda t: _extent_mismatch(normpos, t))
    camera = _context(camera, opts)
    fits: list[TemplateFit] = []
    for t in chosen:
        floor = opts.class_ambiguity_ratio * max((f.score for f in fits if f.accepted), default=0.0)
        fits.append(_fit_prepared(normpos, t, meas, opts, camera, floor, time.perf_counter()))
    fits.sort(key=lambda f: (f.accepted, f.score), reverse=True)
    best = fits[0]
    if len(fits) > 1 and best.accepted and not normpos.label:
        second = fits[1]
        close = second.score >= opts.class_ambiguity_ratio * best.score
        if second.accepted and close and not _same_shape(best, second):
            best = replace(
                best,
                accepted=False,
                reason=f"ambiguous class: '{best.template.name}' ({best.score:.3f}) and "
                f"'{second.template.name}' ({second.score:.3f}) explain the points equally",
            )
    alternatives = {f.template.name: round(f.score, 4) for f in fits}
    return replace(best, time_s=time.perf_counter() - t0, extra={**best.extra, "candidates": alternatives})


def fit_best_or_raise(
    normpos: NormPosition, library: object, options: FitOptions | None = None, camera: FitContext | None = None
) -> TemplateFit:
    """`fit_best`, raising `FitRejected` (carrying the fit) when no template is accepted."""
    fit = fit_best(normpos, library, options, camera)
    if not fit.accepted:
        raise FitRejected(f"no template accepted: {fit.reason}", fit)
    return fit


def fit_many(
    normposes: Sequence[NormPosition],
    library: object,
    options: FitOptions | None = None,
    camera: FitContext | None = None,
    workers: int = 2,
) -> list[TemplateFit]:
    """`fit_best` of every norm-position (the objects of one frame), in input order, on `workers` threads.

    Objects are fitted in parallel as far as the GIL allows: 62 % of a fit's thread CPU runs in compiled kernels
    that release it (the rest is Python and numpy between them), so 2 workers on 2 idle cores fit a frame about
    1.6x as fast as a loop (277 -> 170-179 ms per 10 objects at load 0.5; `bench_fit.py --gil-share`), not 2x; on a
    loaded machine less. workers <= 1 fits one after the other. Results equal `fit_best`'s.
    """
    templates = list(library)  # type: ignore[call-overload]
    if not templates:
        raise TemplateError("the template library is empty; load templates with load_library(path)")
    if workers < 0:
        raise InputError(f"workers must be >= 0, got {workers}")
    nps = list(normposes)
    labels = {n.label for n in nps}
    # build the per-template caches once, before the threads race for them (the preparation and the sorted
    # exact-nearest candidates, ~70 ms per template on first use)
    for t in templates:
        if "" in labels or labels & {t.label, t.name}:
            candidates(prepare(t))
    if workers <= 1 or len(nps) <= 1:
        return [fit_best(n, templates, options, camera) for n in nps]
    with ThreadPoolExecutor(max_workers=min(workers, len(nps)), thread_name_prefix="fit") as pool:
        return list(pool.map(lambda n: fit_best(n, templates, options, camera), nps))


# -- internals -------------------------------------------------------------------------------------


class _TooFew(Exception):
    pass


def _context(camera: FitContext | None, opts: FitOptions) -> FitContext | None:
    """The context with a float64 depth image, corrected by `depth_bias_m` (done once per object, not per pose)."""
    if camera is None:
        return None
    d = np.ascontiguousarray(camera.depth_m, dtype=np.float64)
    if opts.depth_bias_m:
        d = np.where(d > 0, d - opts.depth_bias_m, 0.0)
    return camera if d is camera.depth_m else FitContext(camera.camera, d)


def _prepare_measurement(normpos: NormPosition, opts: FitOptions) -> _Measured:
    pts = np.asarray(normpos.points, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normpos.normals, dtype=np.float64).reshape(-1, 3)
    good = np.all(np.isfinite(pts), axis=1)
    if nrm.shape == pts.shape:
        good &= np.all(np.isfinite(nrm), axis=1)
    pts = pts[good]
    if len(pts) < opts.min_points:
        raise _TooFew(f"too few points: {len(pts)} valid measured points, need at least {opts.min_points}")
    vp = np.asarray(normpos.viewpoint, dtype=np.float64).reshape(3)
    if opts.depth_bias_m:
        ray = pts - vp
        rl = np.linalg.norm(ray, axis=1, keepdims=True)
        z_along = _view_axis_cos(ray, rl)
        pts = pts - ray / np.maximum(rl, 1e-9) * (opts.depth_bias_m / z_along)[:, None]
    if nrm.shape[0] == good.shape[0]:
        nrm = nrm[good]
    nlen = np.linalg.norm(nrm, axis=1) if nrm.shape == pts.shape else np.zeros(len(pts))
    if nrm.shape != pts.shape or np.mean(np.abs(nlen - 1.0) < 1e-3) < 0.9:
        nrm = estimate_normals(pts, vp)
    else:
        nrm = nrm / np.where(nlen < 1e-9, 1.0, nlen)[:, None]
    rng = np.random.default_rng(opts.seed)
    rngs = np.linalg.norm(pts - vp, axis=1)
    thr_all = np.maximum(opts.inlier_distance_m, 2.5 * opts.noise_per_m2 * rngs**2)
    fi = _subsample(len(pts), opts.n_fit_points, rng)
    si = _subsample(len(pts), opts.n_score_points, rng)
    return _Measured(
        pts_fit=pts[fi],
        nrm_fit=nrm[fi],
        thr_fit=thr_all[fi],
        pts_score=pts[si],
        nrm_score=nrm[si],
        thr_score=thr_all[si],
        viewpoint=vp,
        neighbours_score=consistency_neighbours(pts[si]),
        thr_fit_median=float(np.median(thr_all[fi])),
        thr_score_median=float(np.median(thr_all[si])),
        all_pts=pts,
        all_nrm=nrm,
    )


def estimate_normals(points: FloatArray, viewpoint: FloatArray, k: int = 12) -> FloatArray:
    """(N, 3) unit normals of (N, 3) points from their k nearest neighbours, oriented towards `viewpoint`."""
    n = len(points)
    kk = min(k, n)
    _, idx = cKDTree(points).query(points, k=kk)
    nb = points[np.asarray(idx).reshape(n, kk)]
    cen = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", cen, cen)
    _, vec = np.linalg.eigh(cov)
    nrm = vec[:, :, 0]
    flip = np.einsum("ij,ij->i", nrm, viewpoint - points) < 0
    nrm[flip] *= -1
    return nrm


def _view_axis_cos(ray: FloatArray, length: FloatArray) -> FloatArray:
    """cos of the angle between each ray and the mean viewing direction (z-depth -> range along the ray)."""
    axis = ray.mean(axis=0)
    axis = axis / max(float(np.linalg.norm(axis)), 1e-12)
    return np.clip((ray @ axis) / np.maximum(length[:, 0], 1e-9), 0.2, 1.0)


def _subsample(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(rng.choice(n, size=k, replace=False))


def _fit_candidates(
    prep: PreparedTemplate,
    template: Template,
    normpos: NormPosition,
    meas: _Measured,
    opts: FitOptions,
    ctx: FitContext | None,
    floor: float = 0.0,
    starts: FloatArray | None = None,
) -> list[_Candidate]:
    rng = np.random.default_rng(opts.seed + 1)
    hyps = []
    if starts is not None:
        hyps.append(starts)
    else:
        if opts.use_pca:
            hyps.append(_pca_hypotheses(prep, meas))
        if opts.ransac_iterations > 0:
            hyps.append(_ransac(prep, meas, opts, rng))
        if opts.use_control_points and template.control_points:
            hyps.append(control_point_hypotheses(template, meas.all_pts, meas.viewpoint, prep.diameter))
    poses = np.concatenate([h for h in hyps if len(h)], axis=0) if any(len(h) for h in hyps) else np.zeros((0, 4, 4))
    if len(poses) == 0:
        return []
    ci = _subsample(len(meas.pts_fit), opts.n_coarse_points, rng)
    thr_coarse_median = float(np.median(meas.thr_fit[ci]))

    def coarse(start: FloatArray, start_scales: FloatArray, keep_n: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Coarse ICP (grid correspondences, fixed scale) of poses on the coarse subsample, pruned to `keep_n`."""
        return icp(
            prep,
            start,
            start_scales,
            meas.pts_fit[ci],
            meas.nrm_fit[ci],
            meas.thr_fit[ci],
            iterations=opts.coarse_iterations,
            exact=False,
            fit_scale=False,
            scale_tolerance=opts.scale_tolerance,
            max_corr_start=0.25 * prep.diameter,
            prune_after=opts.coarse_prune_after,
            prune_keep=keep_n,
            thr_median=thr_coarse_median,
        )

    poses, scales, frac = coarse(poses, np.ones(len(poses)), opts.coarse_keep)
    # on a part small against the inlier distance the coarse fraction saturates: rank by the score bound there
    saturates = thr_coarse_median > _SATURATING_SHARE * prep.diameter
    rank = _coarse_rank(prep, poses, scales, frac, meas) if saturates else frac
    keep = _distinct(poses, rank, prep, opts.n_refine)
    cff = ctx.camera_from_frame(normpos.frame) if ctx is not None else None
    out, ref_poses, ref_scales = _refine(prep, poses[keep], scales[keep], meas, opts, ctx, cff, [], floor)
    if opts.n_flip_variants > 0 and len(ref_poses):
        # the best pose turned about the template's principal axes (all 24 axis assignments): a view that
        # hides the distinguishing features may have pulled every hypothesis into one wrong basin; the
        # variants either win, tie (-> ambiguous, rejected) or lose clearly
        # (the refined pose of the best coarse hypothesis)
        best = ref_poses[0]
        # turn about the measured surface's centre (object frame): the seen data stay roughly in place
        centre = (best[:3, :3] @ meas.pts_fit.mean(axis=0) + best[:3, 3]) / ref_scales[0]
        variants = []
        for rv in _turns(prep):
            turn = np.eye(4)
            turn[:3, :3] = rv
            turn[:3, 3] = centre - rv @ centre
            variants.append(turn @ best)
        vp, vs, vf = coarse(np.array(variants), np.full(len(variants), ref_scales[0]), opts.flip_keep)
        vr = _coarse_rank(prep, vp, vs, vf, meas) if saturates else vf
        pick = [i for i in _distinct(vp, vr, prep, opts.n_flip_variants + 2) if not _near(vp[i], best, prep)]
        pick = pick[: opts.n_flip_variants]
        if pick:
            out, _, _ = _refine(prep, vp[pick], vs[pick], meas, opts, ctx, cff, out, floor)
    out.sort(key=lambda c: c.score.score, reverse=True)
    if opts.fit_scale and out:
        out[0] = _with_scale(prep, out[0], meas, opts, ctx, cff)
    return out


_NEAR_COS = float(np.cos(np.deg2rad(8)))


#: the coarse inlier fraction saturates where the median inlier distance is more than this share of the part's
#: diameter (7 mm at 0.9 m with D435 noise: a 33 mm bushing or a 45 mm sphere, not the other built-in parts)
_SATURATING_SHARE = 0.15


def _score_bounds(
    prep: PreparedTemplate, poses: FloatArray, scales: FloatArray, meas: _Measured
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """`score_bounds` of object_from_frame poses (H, 4, 4) and scales (H,) on the measurement's score points."""
    return score_bounds(
        prep,
        poses,
        scales,
        meas.pts_score,
        meas.nrm_score,
        meas.thr_score,
        meas.neighbours_score,
        thr_median=meas.thr_score_median,
    )


def _coarse_rank(
    prep: PreparedTemplate, poses: FloatArray, scales: FloatArray, frac: FloatArray, meas: _Measured
) -> FloatArray:
    """(H,) ranking of coarse poses for refinement on parts where the coarse fraction saturates
    (`_SATURATING_SHARE`): the score bound (`score_bounds`: inliers, RMSE, consistency) on the score points, ties
    broken by the coarse inlier fraction. A 2.5 sigma inlier distance of 7 mm at 0.9 m is a fifth of a 34 mm
    bushing: an upside-down pose also scores 1.0 and took the refinement slots from the right one."""
    if len(poses) == 0:
        return frac
    bound, _, _ = _score_bounds(prep, poses, scales, meas)
    return np.asarray(bound + 1e-3 * frac, dtype=np.float64)


def _near(a: FloatArray, b: FloatArray, prep: PreparedTemplate) -> bool:
    """Poses within 5 % of the diameter and 8 degrees of each other."""
    return bool(kernels.poses_near(np.ascontiguousarray(a), np.ascontiguousarray(b), 0.05 * prep.diameter, _NEAR_COS))


def _refine(
    prep: PreparedTemplate,
    poses: FloatArray,
    scales: FloatArray,
    meas: _Measured,
    opts: FitOptions,
    ctx: FitContext | None,
    cff: FloatArray | None,
    scored: list[_Candidate],
    floor: float = 0.0,
) -> tuple[list[_Candidate], FloatArray, FloatArray]:
    """Fine ICP of (H, 4, 4) poses: (`scored` plus the refined poses that may matter, best first; all refined
    poses (H, 4, 4) and scales (H,) in input order).

    Lazy scoring: a pose's score never exceeds its bound (`score_bounds`, one batched query), so poses are scored fully
    in order of that bound and a pose whose bound is below `ambiguity_ratio` x the best score so far is dropped:
    it can be neither the best nor a rival of it (the best score only grows later), so decisions are unchanged.
    A pose whose bound is below `floor` (set by another template in `fit_best`) is dropped too.
    """
    poses, scales, _ = icp(
        prep,
        poses,
        scales,
        meas.pts_fit,
        meas.nrm_fit,
        meas.thr_fit,
        iterations=opts.icp_iterations,
        exact=False,
        exact_last=opts.exact_iterations,
        fit_scale=False,
        scale_tolerance=opts.scale_tolerance,
        max_corr_start=0.15 * prep.diameter,
        trim=opts.fine_trim,
        thr_median=meas.thr_fit_median,
    )
    bound, res, dist = _score_bounds(prep, poses, scales, meas)
    out = list(scored)
    best = max((c.score.score for c in out), default=0.0)
    for i in np.argsort(-bound, kind="stable"):
        if (out and bound[i] < opts.ambiguity_ratio * best) or bound[i] < floor:
            break
        cand = _evaluate(prep, poses[i], float(scales[i]), meas, ctx, cff, (res[i], dist[i]))
        out.append(cand)
        best = max(best, cand.score.score)
    out.sort(key=lambda c: c.score.score, reverse=True)
    return out, poses, scales


def _with_scale(
    prep: PreparedTemplate,
    cand: _Candidate,
    meas: _Measured,
    opts: FitOptions,
    ctx: FitContext | None,
    cff: FloatArray | None,
) -> _Candidate:
    """`cand` refitted with a size factor, kept only when the data clearly ask for one."""
    sp, ss, _ = icp(
        prep,
        cand.object_from_frame[None],
        np.array([cand.scale]),
        meas.pts_fit,
        meas.nrm_fit,
        meas.thr_fit,
        iterations=opts.scale_iterations,
        exact=True,
        fit_scale=True,
        scale_tolerance=opts.scale_tolerance,
        max_corr_start=3.0 * meas.thr_fit_median,
        thr_median=meas.thr_fit_median,
    )
    if abs(float(ss[0]) - 1.0) < 0.005:
        return cand
    scaled = _evaluate(prep, sp[0], float(ss[0]), meas, ctx, cff)
    better = scaled.score.rmse_m < opts.scale_rmse_gain * cand.score.rmse_m
    return scaled if better and scaled.score.score >= cand.score.score else cand


def _evaluate(
    prep: PreparedTemplate,
    pose: FloatArray,
    scale: float,
    meas: _Measured,
    ctx: FitContext | None,
    cff: FloatArray | None,
    corr: tuple[FloatArray, FloatArray] | None = None,
) -> _Candidate:
    sc = evaluate(
        prep,
        pose,
        scale,
        meas.pts_score,
        meas.nrm_score,
        meas.thr_score,
        meas.tree if ctx is None else None,
        meas.viewpoint,
        camera=ctx.camera if ctx is not None else None,
        depth_m=ctx.depth_m if ctx is not None else None,
        camera_from_frame=cff,
        neighbours=meas.neighbours_score,
        corr=corr,
        thr_median=meas.thr_score_median,
    )
    return _Candidate(pose, scale, sc)


def _pca_hypotheses(prep: PreparedTemplate, meas: _Measured) -> FloatArray:
    pts = meas.pts_fit
    c = pts.mean(axis=0)
    cov = np.cov((pts - c).T)
    w, v = np.linalg.eigh(cov)
    am = v[:, np.argsort(w)[::-1]]
    if np.linalg.det(am) < 0:
        am[:, 2] *= -1
    view = c - meas.viewpoint
    view = view / max(float(np.linalg.norm(view)), 1e-12)
    rots = np.einsum("ij,njk,kl->nil", prep.axes, np.array(_SIGNED_PERMS), am.T)  # object_from_frame rotations
    v_obj = rots @ view  # (24, 3) viewing direction in the object frame
    vis = (prep.normals @ v_obj.T < -0.1).astype(np.float64)  # (S, 24) samples facing the camera
    cnt = vis.sum(axis=0)
    cv = np.where(cnt[:, None] > 0, (vis.T @ prep.samples) / np.maximum(cnt, 1.0)[:, None], prep.centroid)
    out = np.tile(np.eye(4), (len(rots), 1, 1))
    out[:, :3, :3] = rots
    out[:, :3, 3] = cv - rots @ c
    return out


def _signed_perms() -> list[FloatArray]:
    out = []
    for perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        for sx in (1, -1):
            for sy in (1, -1):
                for sz in (1, -1):
                    m = np.zeros((3, 3))
                    m[0, perm[0]] = sx
                    m[1, perm[1]] = sy
                    m[2, perm[2]] = sz
                    if np.linalg.det(m) > 0:
                        out.append(m)
    return out


_SIGNED_PERMS = _signed_perms()
_TURNS: weakref.WeakKeyDictionary[PreparedTemplate, list[FloatArray]] = weakref.WeakKeyDictionary()
_TURNS_LOCK = threading.Lock()


def _turns(prep: PreparedTemplate) -> list[FloatArray]:
    """The 23 turns about the template's principal axes (axes d axes^T, d the non-identity signed permutations),
    computed once per template."""
    with _TURNS_LOCK:
        hit = _TURNS.get(prep)
        if hit is None:
            hit = [prep.axes @ d @ prep.axes.T for d in _SIGNED_PERMS[1:]]
            _TURNS[prep] = hit
    return hit


def _ransac(prep: PreparedTemplate, meas: _Measured, opts: FitOptions, rng: np.random.Generator) -> FloatArray:
    keep = voxel_downsample(meas.all_pts, prep.voxel)
    if len(keep) < 6:
        return np.zeros((0, 4, 4))
    mp = meas.all_pts[keep]
    desc = fpfh(mp, meas.all_nrm[keep], prep.voxel * 2.5)
    tol = max(3.0 * meas.thr_fit_median, 0.06 * prep.diameter)
    poses = ransac_hypotheses(
        mp,
        desc,
        prep.samples[prep.desc_idx],
        prep.desc_tree,
        n_iter=opts.ransac_iterations,
        tol=tol,
        min_edge=0.15 * prep.diameter,
        rng=rng,
    )
    if len(poses) == 0:
        return poses
    # quick score on the distance grid: share of points near the surface
    sub = np.ascontiguousarray(mp[_subsample(len(mp), 60, rng)])
    ok = kernels.near_surface_share(
        np.ascontiguousarray(poses),
        sub,
        prep.samples,
        prep.grid_origin,
        float(prep.grid_cell),
        prep.grid_index,
        2.0 * tol,
    )
    top = np.argsort(-ok)[:16]
    return poses[top]


def _distinct(poses: FloatArray, frac: FloatArray, prep: PreparedTemplate, n: int) -> list[int]:
    """Up to n indices of poses, highest `frac` first, none `_near` an earlier one."""
    order = np.argsort(-frac)
    chosen = kernels.distinct_poses(np.ascontiguousarray(poses), order, 0.05 * prep.diameter, _NEAR_COS, n)
    return [int(i) for i in chosen]


def _add_s(prep: PreparedTemplate, a: _Candidate, b: _Candidate) -> float:
    """Symmetry-aware distance between two poses: mean closest-point distance of the posed samples, metres."""
    sub = prep.samples[:: max(1, len(prep.samples) // 300)]
    pa = (sub * a.scale - a.object_from_frame[:3, 3]) @ a.object_from_frame[:3, :3]
    pb = (sub * b.scale - b.object_from_frame[:3, 3]) @ b.object_from_frame[:3, :3]
    return float(kernels.mean_closest(np.ascontiguousarray(pa), np.ascontiguousarray(pb)))


def _add_sym(prep: PreparedTemplate, a: _Candidate, b: _Candidate) -> float:
    """Smallest ADD (mean distance of corresponding posed samples, metres) over the discrete symmetries.

    ADD-S calls a box turned 90 degrees "near" the right pose (its faces overlap the right pose's faces), so
    for templates without a continuous symmetry the rival test also uses this distance.
    """
    sub = prep.samples[:: max(1, len(prep.samples) // 300)]
    pa = (sub * a.scale - a.object_from_frame[:3, 3]) @ a.object_from_frame[:3, :3]
    return float(
        kernels.add_sym(
            np.ascontiguousarray(sub),
            prep.sym,
            np.ascontiguousarray(pa),
            float(b.scale),
            np.ascontiguousarray(b.object_from_frame),
        )
    )


def _decide(
    prep: PreparedTemplate,
    template: Template,
    normpos: NormPosition,
    cands: list[_Candidate],
    opts: FitOptions,
    ctx: FitContext | None,
    t0: float,
) -> TemplateFit:
    best = cands[0]
    s = best.score
    tol = float(
        np.median(
            np.maximum(
                opts.inlier_distance_m,
                2.5
                * opts.noise_per_m2
                * np.linalg.norm(normpos.points[:: max(1, len(normpos.points) // 200)] - normpos.viewpoint, axis=1)
                ** 2,
            )
        )
    )
    reasons = []
    if s.inlier_ratio < opts.min_inlier_ratio:
        reasons.append(f"inlier ratio {s.inlier_ratio:.2f} < {opts.min_inlier_ratio}")
    if s.consistency < opts.min_consistency:
        reasons.append(
            f"systematic residuals: only {s.consistency:.2f} of the points match the template within noise "
            f"after local averaging (< {opts.min_consistency})"
        )
    if s.rmse_m > tol + opts.max_rmse_m:
        reasons.append(f"rmse {s.rmse_m * 1000:.2f} mm > {(tol + opts.max_rmse_m) * 1000:.2f} mm")
    min_cov = opts.min_coverage if ctx is not None else opts.min_coverage_no_depth
    if s.coverage < min_cov:
        reasons.append(f"visible-surface coverage {s.coverage:.2f} < {min_cov}")
    if ctx is not None and s.explained_share < opts.min_explained_share:
        reasons.append(
            f"explained share {s.explained_share:.2f} < {opts.min_explained_share} (most of the model's visible "
            "surface is occluded, off the image or unmeasured)"
        )
    if ctx is not None and s.front_share > opts.max_front_share:
        reasons.append(
            f"unexplained surface {s.front_share:.3f} > {opts.max_front_share} (the model lies right behind "
            "measured points it does not explain)"
        )
    if s.free_space_violation > opts.max_free_space_violation:
        reasons.append(
            f"free-space violation {s.free_space_violation:.2f} > {opts.max_free_space_violation} "
            "(template surface in front of measured depth)"
        )
    rival = None
    for other in cands[1:]:
        if other.score.score >= opts.ambiguity_ratio * s.score and s.score > 0:
            dist = _add_s(prep, best, other)
            if dist > opts.ambiguity_add_s * prep.diameter:
                rival = (other, dist, "ADD-S")
                break
            if not template.symmetry.continuous:
                dist = _add_sym(prep, best, other)
                if dist > opts.ambiguity_add * prep.diameter:
                    rival = (other, dist, "ADD")
                    break
    if rival is not None:
        reasons.append(
            f"ambiguous: a pose {rival[1] * 1000:.1f} mm ({rival[2]}) away scores {rival[0].score.score:.3f} "
            f"vs {s.score:.3f}"
        )
    world_from_object = invert_pose(best.object_from_frame)
    return TemplateFit(
        template=template,
        frame_from_object=world_from_object,
        score=s.score if not reasons else min(s.score, 0.5 * s.score),
        rmse_m=s.rmse_m,
        inlier_ratio=s.inlier_ratio,
        coverage=s.coverage,
        free_space_violation=s.free_space_violation,
        accepted=not reasons,
        reason="; ".join(reasons),
        scale=best.scale,
        frame=normpos.frame,
        instance_id=normpos.instance_id,
        time_s=time.perf_counter() - t0,
        extra={
            "n_points": normpos.n_points,
            "n_candidates": len(cands),
            "candidate_scores": [round(c.score.score, 4) for c in cands],
            "occluded_share": s.occluded_share,
            "consistency": s.consistency,
            "explained_share": s.explained_share,
            "front_share": s.front_share,
            "scale_note": "" if abs(best.scale - 1.0) < 0.005 else f"part is {100 * (best.scale - 1):+.1f} % vs CAD",
        },
    )


def _rejected(template: Template, normpos: NormPosition, reason: str, t0: float) -> TemplateFit:
    pose = np.eye(4)
    if normpos.n_points:
        pose[:3, 3] = np.nan_to_num(np.asarray(normpos.centroid, dtype=np.float64))
    return TemplateFit(
        template=template,
        frame_from_object=pose,
        score=0.0,
        rmse_m=float("inf"),
        inlier_ratio=0.0,
        coverage=0.0,
        free_space_violation=0.0,
        accepted=False,
        reason=reason,
        frame=normpos.frame,
        instance_id=normpos.instance_id,
        time_s=time.perf_counter() - t0,
    )


def _size_compatible(normpos: NormPosition, template: Template, opts: FitOptions) -> bool:
    prep = prepare(template)
    ext = float(np.max(np.asarray(normpos.obb.extents, dtype=np.float64)))
    return ext <= prep.diameter * (1.0 + opts.scale_tolerance) + 0.01


def _extent_mismatch(normpos: NormPosition, template: Template) -> float:
    """How far the measured OBB extents lie from the template's principal extents (log ratio, two largest)."""
    prep = prepare(template)
    ext_t = np.sort(np.ptp(prep.samples @ prep.axes, axis=0))[::-1]
    ext_m = np.sort(np.asarray(normpos.obb.extents, dtype=np.float64))[::-1]
    return float(np.sum(np.abs(np.log(np.maximum(ext_m[:2], 1e-4) / np.maximum(ext_t[:2], 1e-4)))))


def _same_shape(a: TemplateFit, b: TemplateFit) -> bool:
    """Two templates with (nearly) the same geometry are not a class ambiguity."""
    pa, pb = prepare(a.template), prepare(b.template)
    return bool(abs(pa.diameter - pb.diameter) < 0.02 * pa.diameter and a.template.label == b.template.label)
