"""CAD detection in the whole region of interest (`--segmenter cad`): instances found by their templates, no masks.

1. Region of interest: valid depth inside the bin interior (or over the table top) from the cell, minus the support
   plane (points within a noise band of it or behind it); without a cell, the frame's dominant plane is removed.
2. The ROI cloud (camera frame) voxel-averaged at each template's point-pair step, normals from the neighbours.
3. Hypotheses per template from point-pair-feature voting (`templates.ppf`), clustered; each pulled in by a short
   ICP on the scene points near it and ranked by the full-resolution ROI pixels its surface explains.
4. Greedy selection: the hypothesis explaining the most pixels not yet claimed is measured on its explained pixels
   and verified by the existing fit (`templates.fit.fit_template_from`: refinement, turned variants, scoring,
   rival and free-space tests); an accepted pose claims its pixels. Rounds repeat PPF on the unexplained residual
   until a round accepts nothing new. Then every accepted pose is judged against the whole scene and all the
   other accepted poses at once (`CadDetector._contradiction`): one whose measured surface goes on past its
   silhouette (a small template on part of a larger part) or that rests on depth outside the ROI is dropped.
5. Instances: masks rendered from the accepted poses (z-buffered together, kept where measured depth agrees),
   returned with their norm-positions and fits (`CadDetection`) so `pipeline.perceive` does not fit them again.

Segments of another segmenter (`hints`) are optional: in the first round a hint's points are the PPF reference
points and a hint's label (when the library has it) restricts the templates voted for.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.measure.depth_bias import plane_in_camera, support_plane_world
from normpos_grasp.measure.measure import MeasureOptions, backproject_depth, measure_instances
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.template import Template, TemplateFit
from normpos_grasp.templates import kernels, ppf
from normpos_grasp.templates.edges import refine_turn, symmetry_axis
from normpos_grasp.templates.fit import FitContext, FitOptions, estimate_normals, fit_best, fit_template_from
from normpos_grasp.templates.icp import icp
from normpos_grasp.templates.prepared import PreparedTemplate, prepare
from normpos_grasp.typing import BoolArray, FloatArray, IntArray

logger = logging.getLogger(__name__)

__all__ = ["CadDetection", "CadDetector", "CadOptions", "RegionOfInterest"]


@dataclass(frozen=True, eq=False)
class RegionOfInterest:
    """Where parts may lie, world frame (metres).

    plane_world: (4,) support plane n . x + d = 0 (n up, unit) or None (the frame's dominant plane is used);
    world_from_box / box_size: (4, 4) centre pose and (3,) full extents of the box parts lie in (the bin interior
    up to `above_m` over its rim), or None (everything above the plane); plane_camera: (4,) the support plane in
    the camera frame, for a camera without extrinsics (used before plane_world).
    """

    plane_world: FloatArray | None = None
    world_from_box: FloatArray | None = None
    box_size: FloatArray | None = None
    plane_camera: FloatArray | None = None

    @classmethod
    def from_cell(cls, cell: CellConfig, above_m: float = 0.15) -> RegionOfInterest:
        """The bin interior (walls excluded, up to `above_m` over the rim; several bins: the box around all their
        interiors, `CellConfig.bins_region`) or the table top of `cell`."""
        plane = support_plane_world(cell)
        region = cell.bins_region(above_m) if len(cell.bins) > 1 else None
        if region is not None:
            return cls(plane, region[0], region[1])
        if cell.bin is not None:
            lx, ly, h = (float(v) for v in cell.bin.inner_size)
            centre = np.eye(4)
            centre[2, 3] = (h + above_m) / 2
            return cls(plane, cell.bin.world_from_bin @ centre, np.array([lx, ly, h + above_m]))
        return cls(plane)


@dataclass(frozen=True)
class CadOptions:
    """Settings of `CadDetector`.

    plane_band_m: points within this distance of the support plane (plus 2.5 x the depth noise) are the plane.
    thin_above_m / thin_window_px: a pixel within that band is still a part's (a thin plate lying on the plane) when
        the mean height over the plane of the in-band pixels of its thin_window_px window exceeds thin_above_m
        (metres; 0 disables; `_thin_above`).
    wall_margin_m: the ROI box is shrunk by this much on each side (points on the bin walls), metres.
    ref_every: every ref_every-th downsampled ROI point is a PPF reference point; n_peaks: accumulator peaks kept
        per reference point; hypotheses: clustered hypotheses per template and round.
    pull_in: voted poses per template and round pulled in by ICP.
    refine_peaks: in the depth ranking, this many distinct raw peaks (best depth score first, at most 2 x place_cap
        per place) are refined together (`_refine_batch`: 5 ICP iterations on every second scene point) and scored
        again before the ranking (0: the raw peaks are ranked); place_cap / place_share: at most place_cap ranked
        poses whose centroids lie within place_share x the diameter of each other (0: no cap), so one place of the
        pile (a large surface many wrong poses fit) does not take the whole budget; cluster_max: only the best-voted
        raw peaks go into the vote clustering (its time). With ref_every 2 and n_peaks 4 (raw peaks holding a right
        pose for 24 of bench_cad's 29 seed-2 targets, against 17 with 5 and 2) they took that seed from recall 0.62 /
        precision 0.82 to 0.72 / 0.88 and the unseen seed 5 from 0.47 / 0.70 to 0.53 / 0.80 at the same CPU time.
    ranking: 'both': besides the vote clusters explaining the most downsampled points (`ppf.cluster_poses`, the
        first cut), every raw vote peak is scored on the depth image (`ppf.depth_scores`: the template's visible
        points supported by depth inside the residual ROI, minus those supported outside it, minus 3 x those seen
        through), suppressed to the `hypotheses` best distinct poses (`ppf.nms_poses`), and the `pull_in` best of
        those scoring at least min_rank_share of the best are pulled in too (on bench_cad's piles the right pose
        was among the raw peaks for 17 of 29 targets, among the clusters for 7, among the depth-ranked for 14);
        'depth': the depth-ranked peaks only; 'votes': the clusters only.
    icp_iterations: ICP iterations pulling each hypothesis onto the scene points near it.
    explain_tol_m: a pixel is explained by a pose when its point lies within this distance (plus 2.5 x noise) of
        the posed model surface, metres.
    min_pixels: fewest explained pixels (not claimed by an accepted pose) for a hypothesis to be verified.
    min_new_share: a hypothesis whose explained pixels are less than this share unclaimed is skipped.
    crop_band_m: the fit of a hypothesis measures the unclaimed ROI pixels within the explain tolerance plus this
        band (metres) of the pose, so nearby surfaces the pose does not explain count against it. 0 by default:
        on piles the touching parts' points in a 6 mm band failed right poses on the fit's residual test (bench_cad
        seed 2: recall 0.48 / precision 0.61 with 6 mm, 0.62 / 0.72 with 0; unseen seed 5: 0.37 / 0.50 against
        0.57 / 0.65).
    min_support / max_see_through: a pulled-in pose needs at least this share of its visible unoccluded surface
        supported by depth and at most this share seen through (`_evidence`) to be ranked at all.
    min_score: an accepted fit scoring below this is not taken (the fit's acceptance plus this floor: in the held-out
        benchmark's first precision-against-score table, seed 1, accepted fits below 0.6 were all wrong; the real
        LM-O can scores 0.65, so a higher floor would cost real frames).
    max_sink_m: a hypothesis or fit reaching more than this (plus 2.5 x the noise) below the support plane is
        dropped (`CadDetector._sinks`; metres, 0 disables).
    max_verify: most hypotheses verified per round (the best-explaining first).
    max_continuation / max_off_roi / off_roi_margin_px: when the greedy selection ends, every accepted pose is judged
        against the scene and all the other accepted poses at once (`CadDetector._drop_contradicted`): a pose whose
        measured surface goes on past its silhouette on several sides (`_contradiction`: ring pixels 3-8 px outside
        it, inside the ROI, not explained by another accepted pose, whose 5 x 5 mean depth and normal lie on the
        pose's tangent plane; the third largest share of 8 sectors round the outline) above max_continuation, or
        whose visible samples rest on depth more than off_roi_margin_px outside the ROI (the floor, a wall) for more
        than max_off_roi of them, is a template explaining part of a larger surface (a puck's top disc on a plate or
        a U channel's web, a square plate on a strip plate) or overhanging its part onto the floor, and is dropped;
        0 disables either test. On the held-out piles (bench_cad seeds 2, 5 and 7, no hints, and seed 2 with the
        model's hints; 93 accepted poses with the tests off) the third-sector continuation of every right pose was 0,
        of 9 of the 29 wrong ones 0.026-0.25 (most of the others: another template's pose on a surface it covers
        without overhang, or a wrong turn of the right template: no surface goes on). The mean share over the whole
        ring was tried first: a right square plate touching a strip plate reached 0.059 there, wrong poses
        0.014-0.21. Off-ROI support beyond 4 px: right poses at most 0.023 without hints, one right square plate
        0.109 with the model's hints (3 mm off, over the floor); wrong plates 0.26-0.68 (4 of them), the other wrong
        poses under 0.06. Without the margin right thin plates on the floor reached 0.53 (their outline on floor
        pixels the ROI's window mean erodes).
    max_rounds: PPF rounds on the residual; a round that accepts nothing ends the detection.
    noise_per_m2: depth noise RMS per squared range, 1/m (D435: 0.0036).
    refine_turn: turn accepted poses of templates with a discrete rotation group (nut, square plate, hex standoff)
        about its axis to the best outline evidence (`templates.edges.refine_turn`).
    refine_region / refine_min_gain: then turn and slide accepted poses to the best evidence against the unclaimed
        ROI (`CadDetector._refine_region`), kept when it gains more than refine_min_gain x the visible samples.
    compete: judge every accepted fit against the other templates on the same measured pixels
        (`CadDetector._outcompeted`); a template explaining them better takes its place.
    compete_off_roi: a competing template does not take a fit's place when more of its visible samples than
        this share above the fit's rest on depth outside the ROI (beyond off_roi_margin_px, `CadDetector._off_roi`;
        -1 disables): a template that explains the pixels by resting on the floor beside them does not explain
        them better. On bench_cad seeds 2, 5 and 7 the six replacements made were 2 right (0.000 off the ROI, as
        the fits they replaced) and 4 wrong (0.062-0.224 against 0.000-0.006; 2 of them replaced right hex
        standoffs by a strip plate and an L angle). With 0.03 (3 frames each, no hints): seeds 2 and 5 unchanged,
        7 recall 0.733 -> 0.767 / precision 0.815 -> 0.852, unseen 9 0.600 -> 0.633 / 0.720 -> 0.760, unseen 11
        0.267 both / 0.571 -> 0.533 (a wrong puck kept whose wrong replacement, an L angle, did not survive).
    """

    plane_band_m: float = 0.004
    thin_above_m: float = 0.002
    thin_window_px: int = 15
    wall_margin_m: float = 0.003
    ref_every: int = 2
    n_peaks: int = 4
    hypotheses: int = 24
    pull_in: int = 10
    refine_peaks: int = 48
    place_cap: int = 2
    place_share: float = 0.3
    cluster_max: int = 3000
    ranking: str = "both"
    min_rank_share: float = 0.3
    icp_iterations: int = 8
    explain_tol_m: float = 0.003
    min_pixels: int = 80
    min_new_share: float = 0.6
    max_verify: int = 40
    crop_band_m: float = 0.0
    min_support: float = 0.6
    min_score: float = 0.6
    max_sink_m: float = 0.003
    max_see_through: float = 0.1
    max_rounds: int = 3
    max_continuation: float = 0.02
    max_off_roi: float = 0.15
    off_roi_margin_px: int = 4
    noise_per_m2: float = 0.0036
    refine_turn: bool = True
    refine_region: bool = True
    refine_min_gain: float = 0.005
    compete: bool = True
    compete_off_roi: float = 0.03

    def __post_init__(self) -> None:
        if not (self.ref_every >= 1 and self.n_peaks >= 1 and self.hypotheses >= 1 and self.max_rounds >= 1):
            raise InputError(
                "cad detection needs ref_every, n_peaks, hypotheses and max_rounds >= 1; got "
                f"{self.ref_every}, {self.n_peaks}, {self.hypotheses}, {self.max_rounds}"
            )
        if self.ranking not in ("both", "depth", "votes"):
            raise InputError(f"cad ranking must be 'both', 'depth' or 'votes'; got {self.ranking!r}")
        if not (0.0 < self.min_new_share <= 1.0 and self.explain_tol_m > 0 and self.min_pixels >= 3):
            raise InputError(
                f"need min_new_share in (0, 1], explain_tol_m > 0 and min_pixels >= 3; got {self.min_new_share}, "
                f"{self.explain_tol_m}, {self.min_pixels}"
            )


@dataclass(frozen=True, eq=False)
class CadDetection:
    """What `CadDetector.detect` found: instances (masks from the accepted poses), their norm-positions and fits
    (one each, matched by instance_id), the number of hypotheses voted and verified, of accepted poses dropped by
    the judgement against the whole scene (`CadDetector._drop_contradicted`), and wall times (ms)."""

    instances: list[Instance]
    normpositions: list[NormPosition]
    fits: list[TemplateFit]
    n_hypotheses: int = 0
    n_verified: int = 0
    n_dropped: int = 0
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class _Hyp:
    template: Template
    prep: PreparedTemplate
    camera_from_object: FloatArray
    pixels: IntArray  # flat pixel indices it explains
    votes: float
    quality: float = 1.0  # depth evidence (`CadDetector._evidence`)


class CadDetector:
    """The `cad` segmenter: CAD instances found in the whole region of interest (module docstring).

    library: the templates to detect (or given to `detect` by the pipeline); roi: where parts lie (None: above the
    frame's dominant plane); hints: an optional segmenter whose segments guide the first round.
    """

    def __init__(
        self,
        library: Iterable[Template] | None = None,
        roi: RegionOfInterest | None = None,
        hints: Segmenter | None = None,
        options: CadOptions | None = None,
    ) -> None:
        self.library = list(library) if library is not None else None
        self.roi = roi
        self.hints = hints
        self.options = options or CadOptions()
        self._camera_k = np.eye(3)  # the frame's intrinsics and depth while `detect` runs
        self._depth = np.zeros((1, 1))
        self._plane_c: FloatArray | None = None  # the support plane (camera frame, +: the camera's side)
        #: when a list, `detect` appends (stage, template name, (K, 4, 4) camera_from_object poses) at each stage
        #: of the hypothesis funnel (votes, clusters, prescore, pull_in, verified, accepted; bench_cad_funnel.py)
        self.trace: list[tuple[str, str, FloatArray]] | None = None

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        """The detected instances (labels from the templates, scores from the fits)."""
        return self.detect(frame).instances

    def detect(
        self,
        frame: RGBDFrame,
        library: Iterable[Template] | None = None,
        measure: MeasureOptions | None = None,
        fit: FitOptions | None = None,
        hint_instances: Sequence[Instance] | None = None,
        roi: RegionOfInterest | None = None,
    ) -> CadDetection:
        """Detect the templates of `library` (default: the detector's own) in `frame`. `hint_instances` replace
        the hint segmenter's output (None: run it, when there is one); `roi` replaces the detector's region of
        interest for this frame."""
        templates = list(library) if library is not None else self.library
        if not templates:
            raise InputError("the cad segmenter needs a template library (pass one to CadDetector or to detect)")
        opts = self.options
        fopts = fit or FitOptions()
        mopts = measure or MeasureOptions()
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        cam = frame.camera
        depth = np.asarray(frame.depth_m, dtype=np.float64)
        h, w = depth.shape
        pmap = backproject_depth(cam, depth)
        self._camera_k = np.asarray(cam.K, dtype=np.float64)
        self._depth = np.ascontiguousarray(depth)
        in_roi = self._roi_mask(frame, pmap, roi if roi is not None else self.roi)
        # off-ROI support counts only beyond off_roi_margin_px of the ROI (`_off_roi`)
        near_roi = _dilate(in_roi.reshape(h, w), opts.off_roi_margin_px)
        timings["roi"] = _ms(t0)
        hints = list(hint_instances) if hint_instances is not None else None
        if hints is None and self.hints is not None:
            t1 = time.perf_counter()
            hints = self.hints.segment(frame)
            timings["hints"] = _ms(t1)
        preps = {t.name: prepare(t) for t in templates}
        claimed = np.zeros(h * w, dtype=bool)
        accepted: list[tuple[_Hyp, TemplateFit]] = []
        ctx = FitContext(cam, depth)
        wfc = cam.world_from_camera
        rejected: list[tuple[str, FloatArray]] = []  # (template, posed centroid) of hypotheses that failed
        n_hyp = n_ver = 0
        t_vote = t_verify = 0.0
        for rnd in range(opts.max_rounds):
            t1 = time.perf_counter()
            residual = in_roi & ~_dilate(claimed.reshape(h, w), 2).reshape(-1)
            if residual.sum() < opts.min_pixels:
                break
            hyps = self._hypotheses(pmap, residual, templates, preps, hints if rnd == 0 else None)
            n_hyp += len(hyps)
            t_vote += time.perf_counter() - t1
            t1 = time.perf_counter()
            hyps.sort(key=lambda hy: len(hy.pixels) * hy.quality, reverse=True)
            new = 0
            tried = 0
            for hy in hyps:
                if tried >= opts.max_verify:
                    break
                fresh = ~claimed[hy.pixels]
                n_fresh = int(fresh.sum())
                if n_fresh < opts.min_pixels or n_fresh < opts.min_new_share * len(hy.pixels):
                    continue
                c_hy = hy.camera_from_object[:3, :3] @ hy.prep.centroid + hy.camera_from_object[:3, 3]
                lim = 0.1 * hy.prep.diameter
                if any(n == hy.template.name and np.linalg.norm(c - c_hy) < lim for n, c in rejected):
                    continue  # the same hypothesis failed before (an earlier round)
                tried += 1
                # the fit sees every unclaimed ROI point near the pose, not only those it explains: points of
                # another surface running through the hypothesis count against it
                crop = self._explained(pmap, in_roi & ~claimed, hy.prep, hy.camera_from_object, 1.0, opts.crop_band_m)
                mask = np.zeros(h * w, dtype=bool)
                mask[crop] = True
                mask[hy.pixels[fresh]] = True
                inst = Instance(mask.reshape(h, w), hy.template.label, 1.0, len(accepted) + 1)
                nps = measure_instances(frame, [inst], mopts)
                if not nps:
                    continue
                start = hy.camera_from_object if wfc is None else wfc @ hy.camera_from_object
                res = fit_template_from(nps[0], hy.template, start[None], fopts, ctx)
                n_ver += 1
                if self.trace is not None:
                    self.trace.append(("verified", hy.template.name, hy.camera_from_object[None]))
                if not res.accepted or res.score < opts.min_score:
                    rejected.append((hy.template.name, c_hy))
                    continue
                cfo = res.frame_from_object if wfc is None else invert_pose(wfc) @ res.frame_from_object
                if self._sinks(hy.prep, cfo):
                    rejected.append((hy.template.name, c_hy))
                    continue
                if opts.compete:  # another template explaining the same pixels better takes its place
                    beaten, alt = self._outcompeted(res, nps[0], templates, fopts, ctx, near_roi)
                    if beaten:
                        if self.trace is not None:
                            self.trace.append(("outcompeted", hy.template.name, cfo[None]))
                        rejected.append((hy.template.name, c_hy))
                        if alt is None or alt.score < opts.min_score:
                            continue
                        acfo = alt.frame_from_object if wfc is None else invert_pose(wfc) @ alt.frame_from_object
                        hy = replace(hy, template=alt.template, prep=preps[alt.template.name], camera_from_object=acfo)
                        res, cfo = alt, acfo
                        if self._sinks(hy.prep, cfo):
                            continue
                if opts.refine_turn:  # the turn inside a symmetric family, on the outline (templates.edges)
                    z = float(cfo[2, 3])
                    tol = opts.explain_tol_m + 2.5 * opts.noise_per_m2 * z * z
                    cfo, turn = refine_turn(hy.template, hy.prep, cfo, self._camera_k, depth, tol)
                    if turn:
                        res = replace(
                            res,
                            frame_from_object=cfo if wfc is None else wfc @ cfo,
                            extra={**res.extra, "edge_turn_deg": round(float(np.degrees(turn)), 2)},
                        )
                if opts.refine_region:  # the outline against the region: slides and turns the surface leaves free
                    cfo, moved = self._refine_region(hy.template, hy.prep, cfo, (in_roi & ~claimed).reshape(h, w))
                    if moved:
                        res = replace(
                            res,
                            frame_from_object=cfo if wfc is None else wfc @ cfo,
                            extra={**res.extra, "region_refined": True},
                        )
                px = self._explained(pmap, in_roi, hy.prep, cfo, res.scale)
                if len(px) < opts.min_pixels or np.mean(claimed[px]) > 1.0 - opts.min_new_share:
                    continue
                claimed[px] = True
                accepted.append((replace(hy, camera_from_object=cfo, pixels=px), res))
                if self.trace is not None:
                    self.trace.append(("accepted", hy.template.name, cfo[None]))
                new += 1
            t_verify += time.perf_counter() - t1
            if new == 0 and (rnd > 0 or not hints):
                break  # (a hinted first round that accepts nothing, hints of a wrong label or place, is not the end)
        # the greedy selection is done: every accepted pose judged against all the others (a neighbour accepted in
        # a later round explains the surface beside it)
        t1 = time.perf_counter()
        n_dropped = self._drop_contradicted(pmap, in_roi, accepted)
        t_verify += time.perf_counter() - t1
        timings["vote"] = 1e3 * t_vote
        timings["verify"] = 1e3 * t_verify
        t1 = time.perf_counter()
        out = self._instances(frame, accepted, mopts)
        timings["masks"] = _ms(t1)
        timings["total"] = _ms(t0)
        return CadDetection(out[0], out[1], out[2], n_hyp, n_ver, n_dropped, timings)

    # -- region of interest ------------------------------------------------------------------------
    def _roi_mask(self, frame: RGBDFrame, pmap: FloatArray, roi: RegionOfInterest | None) -> BoolArray:
        """(H * W,) pixels inside `roi` and off the support plane."""
        opts = self.options
        cam = frame.camera
        pts = pmap.reshape(-1, 3)
        z = pts[:, 2]
        valid = z > 0.05
        band = opts.plane_band_m + 2.5 * opts.noise_per_m2 * z**2
        wfc = cam.world_from_camera
        plane_c = None if roi is None or roi.plane_camera is None else np.asarray(roi.plane_camera, dtype=np.float64)
        if plane_c is None and roi is not None and roi.plane_world is not None and wfc is not None:
            plane_c = plane_in_camera(roi.plane_world, wfc)
        if plane_c is None:
            plane_c = _dominant_plane(pts[valid], band[valid])
        self._plane_c = None
        if plane_c is not None:  # oriented towards the camera: parts lie at positive heights
            self._plane_c = np.asarray(plane_c if plane_c[3] >= 0 else -plane_c, dtype=np.float64)
        keep = valid.copy()
        if roi is not None and roi.world_from_box is not None and roi.box_size is not None and wfc is not None:
            box_from_camera = invert_pose(roi.world_from_box) @ wfc
            pb = pts @ box_from_camera[:3, :3].T + box_from_camera[:3, 3]
            half = np.asarray(roi.box_size, dtype=np.float64) / 2 - opts.wall_margin_m
            # the walls are shrunk away, not the floor: the box's bottom is the support plane, and the plane test
            # below decides there (shrinking it too cut the top 3 mm plate lying on the floor out of the ROI)
            half[2] += opts.wall_margin_m + 0.01
            keep &= np.all(np.abs(pb) <= half, axis=1)
        if plane_c is not None:
            n, d = plane_c[:3], plane_c[3]
            # the side of the plane facing the camera (camera at the origin: n . 0 + d = d)
            sign = 1.0 if d >= 0 else -1.0
            height = np.where(keep, sign * (pts @ n + d), 0.0)
            above = height > band
            in_band = keep & ~above & (height >= -band)
            keep &= above | _thin_above(height.reshape(frame.depth_m.shape), in_band, opts).reshape(-1)
        return np.asarray(keep)

    # -- hypotheses ---------------------------------------------------------------------------------
    def _hypotheses(
        self,
        pmap: FloatArray,
        residual: BoolArray,
        templates: list[Template],
        preps: dict[str, PreparedTemplate],
        hints: list[Instance] | None,
    ) -> list[_Hyp]:
        opts = self.options
        pts_all = pmap.reshape(-1, 3)
        idx = np.flatnonzero(residual)
        if len(idx) < 3:
            return []
        hint_px = None
        hint_labels: set[str] = set()
        if hints:
            hint_px = np.zeros(len(pts_all), dtype=bool)
            for hi in hints:
                hint_px |= hi.mask.reshape(-1)
                hint_labels.add(hi.label)
        known = {t.label for t in templates} | {t.name for t in templates}
        restrict = hint_labels <= known and "" not in hint_labels and bool(hint_labels)
        clouds: dict[float, tuple[FloatArray, FloatArray, IntArray]] = {}
        out: list[_Hyp] = []
        region = residual.reshape(pmap.shape[:2])
        for t in templates:
            if restrict and not ({t.label, t.name} & hint_labels):
                continue
            prep = preps[t.name]
            model = ppf.ppf_model(prep)
            # one scene cloud per step class (steps snapped to powers of 1.25): few downsamplings per frame
            voxel = float(1.25 ** np.round(np.log(model.step) / np.log(1.25)))
            if voxel not in clouds:
                clouds[voxel] = _downsample(pts_all[idx], idx, voxel)
            sp, sn, spx = clouds[voxel]
            if len(sp) < 10:
                continue
            refs = ppf.scene_references(len(sp), opts.ref_every)
            if hint_px is not None:
                inside = np.flatnonzero(hint_px[spx])
                refs = inside[:: max(1, opts.ref_every // 2)] if len(inside) else refs
            poses, votes = ppf.vote_poses(model, sp, sn, refs, opts.n_peaks)
            if len(poses) == 0:
                continue
            # the vote clusters explaining the most downsampled points (the first cut's hypotheses) ...
            best = np.argsort(-votes, kind="stable")[: opts.cluster_max]
            cp, cv = ppf.cluster_poses(
                poses[best], votes[best], prep.centroid, 0.1 * prep.diameter, np.deg2rad(15.0), opts.hypotheses,
                prep.sym,
            )  # fmt: skip
            keep = _prescore(prep, cp, sp, opts.explain_tol_m, opts.noise_per_m2, opts.pull_in)
            if opts.ranking != "votes":
                # ... and every raw peak judged on the depth image (compiled, on the model points): on a pile the
                # vote counts say little (flat faces share keys), the depth says which peaks lie on a surface
                # that is there; on the real LM-O frame the can's right pose came from the clusters only, on the
                # held-out piles most right poses from the depth ranking only, so both are pulled in
                sc = ppf.depth_scores(
                    model, poses, self._depth, region, self._camera_k, opts.explain_tol_m, opts.noise_per_m2
                )
                # one place of the pile (a big surface many wrong poses fit) must not take the whole budget; the
                # right raw peak of a part is quantised (12-degree alpha bins, voxel normals) and often scores below
                # wrong poses at its place until it is pulled in, so the best distinct peaks are first refined
                # together (one compiled ICP batch) and ranked again
                d, cap = prep.diameter, opts.place_cap
                if opts.refine_peaks > 0:
                    rp, _ = ppf.nms_poses(
                        poses, sc, prep.centroid, 0.1 * d, np.deg2rad(15.0), opts.refine_peaks, prep.sym,
                        2 * cap, opts.place_share * d,
                    )  # fmt: skip
                    poses_r = self._refine_batch(prep, rp, sp[::2], sn[::2])
                    sc = ppf.depth_scores(
                        model, poses_r, self._depth, region, self._camera_k, opts.explain_tol_m, opts.noise_per_m2
                    )
                else:
                    poses_r = poses
                dp, dv = ppf.nms_poses(
                    poses_r, sc, prep.centroid, 0.1 * d, np.deg2rad(15.0), opts.hypotheses, prep.sym,
                    cap, opts.place_share * d,
                )  # fmt: skip
                top = np.flatnonzero(dv >= opts.min_rank_share * dv[0])[: opts.pull_in] if len(dv) else np.zeros(0, int)
                both = np.concatenate([cp[keep], dp[top]]) if opts.ranking == "both" else dp[top]
                rank = np.arange(len(both), 0, -1, dtype=np.float64)  # clusters first, then the depth ranking
                cp, cv = ppf.nms_poses(both, rank, prep.centroid, 0.05 * prep.diameter, np.deg2rad(5.0), len(both))
                keep = np.arange(len(cp))
            pulled = self._pull_in(t, prep, cp[keep], cv[keep], sp, sn, pmap, residual)
            if self.trace is not None:
                self.trace.append(("votes", t.name, poses))
                self.trace.append(("clusters", t.name, cp))
                self.trace.append(("prescore", t.name, cp[keep]))
                self.trace.append(("pull_in", t.name, _stack([hy.camera_from_object for hy in pulled])))
            out.extend(pulled)
        return out

    def _refine_batch(self, prep: PreparedTemplate, poses: FloatArray, sp: FloatArray, sn: FloatArray) -> FloatArray:
        """(K, 4, 4) camera_from_object poses pulled in together by 5 ICP iterations on the scene cloud (sp, sn: (N,
        3) points and normals, metres; one compiled batch, correspondences gated from 0.1 diameter down)."""
        opts = self.options
        if len(poses) == 0:
            return poses
        thr = np.maximum(opts.explain_tol_m, 2.5 * opts.noise_per_m2 * sp[:, 2] ** 2)
        ofc, _, _ = icp(
            prep,
            np.asarray(np.linalg.inv(poses), dtype=np.float64),
            np.ones(len(poses)),
            sp,
            sn,
            thr,
            iterations=5,
            exact=False,
            fit_scale=False,
            scale_tolerance=0.0,
            max_corr_start=0.1 * prep.diameter,
        )
        return np.asarray(np.linalg.inv(ofc), dtype=np.float64)

    def _pull_in(
        self,
        template: Template,
        prep: PreparedTemplate,
        poses: FloatArray,
        votes: FloatArray,
        sp: FloatArray,
        sn: FloatArray,
        pmap: FloatArray,
        residual: BoolArray,
    ) -> list[_Hyp]:
        """Each voted pose refined by ICP on the downsampled scene points near it, with the pixels it explains."""
        opts = self.options
        out = []
        for pose, v in zip(poses, votes, strict=True):
            c = pose[:3, :3] @ prep.centroid + pose[:3, 3]
            near = np.linalg.norm(sp - c, axis=1) < 0.6 * prep.diameter
            if near.sum() < 6:
                continue
            thr = np.maximum(opts.explain_tol_m, 2.5 * opts.noise_per_m2 * sp[near, 2] ** 2)
            ofc, _, _ = icp(
                prep,
                invert_pose(pose)[None],
                np.ones(1),
                sp[near],
                sn[near],
                thr,
                iterations=opts.icp_iterations,
                exact=False,
                fit_scale=False,
                scale_tolerance=0.0,
                max_corr_start=0.1 * prep.diameter,
            )
            cfo = invert_pose(ofc[0])
            if self._sinks(prep, cfo):
                continue
            quality = self._evidence(prep, cfo)
            if quality <= 0.0:
                continue
            px = self._explained(pmap, residual, prep, cfo, 1.0)
            if len(px) >= opts.min_pixels:
                out.append(_Hyp(template, prep, cfo, px, float(v), quality))
        return out

    def _outcompeted(
        self,
        fit: TemplateFit,
        measured: NormPosition,
        templates: Sequence[Template],
        fopts: FitOptions,
        ctx: FitContext,
        near_roi: BoolArray | None = None,
    ) -> tuple[bool, TemplateFit | None]:
        """(whether another template explains the `measured` pixels of an accepted `fit` better, that template's
        fit when it is accepted): competing templates judged on the same evidence (issue 16 item 2). The other
        templates whose size suits the measurement compete on it as on a model-free segment (`templates.fit.
        fit_best`, label ''): their own hypotheses, refinement, scores and free-space, coverage and rival tests.
        `fit` is beaten when their best scores above it and is accepted, or is rejected only for an equally good
        second template (then neither wins). A template posed on part of a larger part (a nut on a puck's top
        face) fits the pixels it explains, but the part's own template fits them better. With `near_roi` ((H, W)
        bool, the ROI grown by off_roi_margin_px), an accepted winner whose camera-facing samples rest on depth
        outside it (`_off_roi`: the floor, a wall) for more than `compete_off_roi` above `fit`'s share does not
        take the place: it explains the pixels by resting on the floor beside them (on bench_cad's piles a strip
        plate and an L angle took right hex standoffs' places so)."""
        others = [t for t in templates if t.name != fit.template.name]
        if not others:
            return False, None
        alt = fit_best(replace(measured, label=""), others, fopts, ctx)
        # 'ambiguous class': two other templates explain the pixels better than `fit` and about equally: `fit` is
        # beaten, but neither of them wins
        beaten = alt.accepted or alt.reason.startswith("ambiguous class")
        if not beaten or alt.score <= fit.score:
            return False, None
        lim = self.options.compete_off_roi
        if alt.accepted and near_roi is not None and lim >= 0:
            cff = ctx.camera_from_frame(measured.frame)
            depth, k = np.ascontiguousarray(ctx.depth_m, dtype=np.float64), np.asarray(ctx.camera.K, dtype=np.float64)

            def off(f: TemplateFit) -> float:
                cfo = cff @ np.asarray(f.frame_from_object, dtype=np.float64)
                return self._off_roi(prepare(f.template), cfo, f.scale, near_roi, depth, k)

            if off(alt) > off(fit) + lim:
                return False, None
        return True, alt if alt.accepted else None

    def _refine_region(
        self, template: Template, prep: PreparedTemplate, cfo: FloatArray, inside: BoolArray
    ) -> tuple[FloatArray, bool]:
        """The pose turned and slid where the surface leaves it free, to the best region evidence of its visible
        samples (`ppf.depth_counts`: supported inside the unclaimed ROI, minus supported outside it, minus 3 x seen
        through): a template with a symmetry axis of order >= 3 turns about it within half a period (2-degree
        steps); a flat one (`_is_flat`) turns about the viewing ray within +-15 degrees (3-degree steps, when it has
        no such axis) and slides across the ray within +-8 % of the diameter; twice in turn. A plate lying on the
        floor is supported by the floor wherever it is slid: only the region's outline fixes its slide and turn.
        Other templates are left as they are. Returns (camera_from_object, whether it moved)."""
        opts = self.options
        pts = prep.samples[::2]
        nrm = prep.normals[::2]
        depth = self._depth

        def counts(poses: FloatArray) -> IntArray:
            return ppf.depth_counts(
                pts, nrm, poses, depth, inside, self._camera_k, opts.explain_tol_m, opts.noise_per_m2
            )

        def score(poses: FloatArray) -> FloatArray:
            c = counts(poses)
            return np.asarray(c[:, 0] - c[:, 1] - 3.0 * c[:, 2], dtype=np.float64)

        found = symmetry_axis(template)
        flat = _is_flat(prep)
        if found is None and not flat:
            return np.asarray(cfo, dtype=np.float64), False  # the surface fixes the pose: nothing left free
        if found is not None:
            half = np.rad2deg(found[1]) / 2
            turns = np.deg2rad(np.arange(-half, half + 1e-9, 2.0))
        else:
            turns = np.deg2rad(np.arange(-15.0, 15.0 + 1e-9, 3.0))
        d = prep.diameter
        offs = np.arange(-0.08 * d, 0.08 * d + 1e-9, max(0.01 * d, 0.001))
        cur = np.asarray(cfo, dtype=np.float64)
        c0 = counts(cur[None])[0]
        base = float(c0[0] - c0[1] - 3.0 * c0[2])
        best = base
        for _ in range(2):
            c = cur[:3, :3] @ prep.centroid + cur[:3, 3]
            ray = c / max(float(np.linalg.norm(c)), 1e-9)
            ax = ray if found is None else cur[:3, :3] @ found[0]
            cand = np.stack([_turned(cur, ax, c, float(t)) for t in turns])
            sc = score(cand)
            i = int(np.argmax(sc))
            if sc[i] > best:
                best, cur = float(sc[i]), cand[i]
            if not flat:
                continue
            e1 = np.cross(ray, [1.0, 0.0, 0.0] if abs(ray[0]) < 0.9 else [0.0, 1.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(ray, e1)
            a, b = np.meshgrid(offs, offs, indexing="ij")
            shift = a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2
            cand = np.repeat(cur[None], len(shift), axis=0)
            cand[:, :3, 3] += shift
            sc = score(cand)
            i = int(np.argmax(sc))
            if sc[i] > best:
                best, cur = float(sc[i]), cand[i]
        if best <= base + opts.refine_min_gain * max(int(c0[3]), 1):
            return np.asarray(cfo, dtype=np.float64), False
        return cur, True

    def _drop_contradicted(self, pmap: FloatArray, in_roi: BoolArray, accepted: list[tuple[_Hyp, TemplateFit]]) -> int:
        """Drop from `accepted` the poses `_contradiction` refutes, each judged against all the other accepted poses
        at once (not one drop after another: a wrong pose dropped leaves its part's surface unexplained, and the
        right pose of the touching part beside it would then see that surface go on; bench_cad seed 7 lost a right
        square plate so, at 0.16 continuation). Returns how many were dropped. (A further round on the dropped
        poses' pixels was tried: on bench_cad seeds 2, 5 and 7 it accepted 4 more poses, all wrong.)"""
        opts = self.options
        if not accepted or (opts.max_continuation <= 0 and opts.max_off_roi <= 0):
            return 0
        h, w = pmap.shape[:2]
        # off-ROI support counts only beyond off_roi_margin_px of the ROI: a right plate's outline lies on floor
        # pixels the ROI's window mean eroded, and a right pose a few millimetres off overhangs the ROI as much
        near = _dilate(in_roi.reshape(h, w), opts.off_roi_margin_px).reshape(-1)
        owner = np.full(h * w, -1, dtype=np.int64)
        for k, (hy, _) in enumerate(accepted):
            owner[hy.pixels] = k
        keep: list[tuple[_Hyp, TemplateFit]] = []
        for k, (hy, f) in enumerate(accepted):
            others = (owner >= 0) & (owner != k)
            cont, off = self._contradiction(pmap, in_roi, others, hy.prep, hy.camera_from_object, f.scale, near)
            if (opts.max_continuation > 0 and cont > opts.max_continuation) or (
                opts.max_off_roi > 0 and off > opts.max_off_roi
            ):
                if self.trace is not None:
                    self.trace.append(("dropped", hy.template.name, hy.camera_from_object[None]))
                continue
            keep.append((hy, f))
        n = len(accepted) - len(keep)
        accepted[:] = keep
        return n

    def _contradiction(
        self,
        pmap: FloatArray,
        in_roi: BoolArray,
        others: BoolArray,
        prep: PreparedTemplate,
        cfo: FloatArray,
        scale: float,
        near_roi: BoolArray | None = None,
    ) -> tuple[float, float]:
        """(continuation, off-ROI support) of a posed template against the measured scene, given the (H * W,)
        pixels `others` explained by other accepted poses. Continuation: of the valid pixels in a ring 3-8 px
        outside its silhouette (its visible samples projected, closed), those inside the ROI, not explained by
        another pose, whose 5 x 5 mean depth puts them within half the explain tolerance plus twice that mean's
        noise of the tangent plane of the nearest visible sample, with a normal within 25 degrees of its: the
        surface the pose claims goes on where the template has ended; their share in each of 8 sectors round the
        silhouette's centre, the third largest returned (several sides, not one touching neighbour). Off-ROI
        support: the share of its visible samples supported by depth outside `near_roi` (default: the ROI;
        `ppf.depth_counts`)."""
        import cv2

        opts = self.options
        h, w = pmap.shape[:2]
        k = self._camera_k
        pv, nv = kernels.visible_points(prep.samples, prep.normals, np.ascontiguousarray(cfo), scale, prep.spacing)
        if len(pv) < 3:
            return 0.0, 0.0
        roi2 = in_roi.reshape(h, w)
        off = self._off_roi(prep, cfo, scale, roi2 if near_roi is None else near_roi)
        uv = kernels.project_pinhole(pv, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        ui = np.round(uv).astype(np.int64)
        m = 9  # the ring's outer radius plus a margin
        u0, v0 = max(int(ui[:, 0].min()) - m, 0), max(int(ui[:, 1].min()) - m, 0)
        u1, v1 = min(int(ui[:, 0].max()) + m + 1, w), min(int(ui[:, 1].max()) + m + 1, h)
        if u1 <= u0 or v1 <= v0:
            return 0.0, off
        ok = (ui[:, 0] >= u0) & (ui[:, 0] < u1) & (ui[:, 1] >= v0) & (ui[:, 1] < v1)
        sil = np.zeros((v1 - v0, u1 - u0), np.uint8)
        sil[ui[ok, 1] - v0, ui[ok, 0] - u0] = 1
        sil = cv2.morphologyEx(cv2.dilate(sil, np.ones((3, 3), np.uint8)), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))

        def grown(r: int) -> BoolArray:
            ker = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            return np.asarray(cv2.dilate(sil, ker) > 0)

        # the depth averaged over the valid pixels of a 5 x 5 window (at least half of them valid): a 3 mm step
        # to the part below stands clear of its noise, so only a surface that truly goes on counts
        depth = self._depth[v0:v1, u0:u1]
        valid = (depth > 0).astype(np.float64)
        num = cv2.boxFilter(depth * valid, -1, (5, 5), normalize=False, borderType=cv2.BORDER_CONSTANT)
        den = cv2.boxFilter(valid, -1, (5, 5), normalize=False, borderType=cv2.BORDER_CONSTANT)
        ok_s = (depth > 0) & (den >= 13)
        vv, uu = np.nonzero(grown(8) & ~grown(3) & ok_s)
        if len(vv) == 0:
            return 0.0, off
        from scipy.spatial import cKDTree

        _, j = cKDTree(uv).query(np.stack([uu + u0, vv + v0], axis=1).astype(np.float64))
        scale_s = np.where(ok_s, num / np.maximum(den, 1.0) / np.where(depth > 0, depth, 1.0), 0.0)
        ps = pmap[v0:v1, u0:u1] * scale_s[:, :, None]  # the mean depth along each pixel's ray
        p = ps[vv, uu]
        offset = np.abs(np.einsum("ij,ij->i", nv[j], p - pv[j]))
        # the scene's normal there (central differences 2 px apart on the mean depth) must agree with the tangent
        # plane's too: a neighbour's surface merely crossing that plane is no continuation
        g = 2
        hh, ww = depth.shape
        a0, a1 = np.clip(uu - g, 0, ww - 1), np.clip(uu + g, 0, ww - 1)
        b0, b1 = np.clip(vv - g, 0, hh - 1), np.clip(vv + g, 0, hh - 1)
        n_s = np.cross(ps[vv, a1] - ps[vv, a0], ps[b1, uu] - ps[b0, uu])
        have = ok_s[vv, a0] & ok_s[vv, a1] & ok_s[b0, uu] & ok_s[b1, uu]
        ln = np.linalg.norm(n_s, axis=1)
        cos = np.abs(np.einsum("ij,ij->i", n_s, nv[j])) / np.maximum(ln, 1e-12)
        along = have & (cos > np.cos(np.deg2rad(25.0)))
        z = float(np.median(pv[:, 2]))
        tol = 0.5 * opts.explain_tol_m + 2.0 * opts.noise_per_m2 * z * z / 5.0  # the noise of a 25-pixel mean
        flat = (vv + v0) * w + (uu + u0)
        goes_on = roi2.reshape(-1)[flat] & ~others[flat] & (offset < tol) & along
        # spread round the outline: 8 sectors about the silhouette's centre, the third largest share. A part
        # touching a coplanar neighbour (two plates side by side on the floor) continues along one side, one to
        # three sectors; a template on part of a larger surface continues on several sides
        cu, cv = float(np.mean(ui[:, 0])) - u0, float(np.mean(ui[:, 1])) - v0
        sector = ((np.arctan2(vv - cv, uu - cu) + np.pi) * (8 / (2 * np.pi))).astype(np.int64) % 8
        n_all = np.bincount(sector, minlength=8)
        n_on = np.bincount(sector, weights=goes_on.astype(np.float64), minlength=8)
        share = np.sort(n_on / np.maximum(n_all, 1))[::-1]
        return float(share[2]), off

    def _off_roi(
        self,
        prep: PreparedTemplate,
        cfo: FloatArray,
        scale: float,
        near_roi: BoolArray,
        depth: FloatArray | None = None,
        k: FloatArray | None = None,
    ) -> float:
        """The share of the posed (camera_from_object) template's camera-facing samples whose pixel's depth agrees
        with them outside `near_roi` ((H, W) or (H * W,) bool: the ROI grown by off_roi_margin_px): the pose rests
        on the floor, a wall or a claimed part there (`ppf.depth_counts`; depth (H, W) metres and intrinsics k
        (3, 3) default to the frame `detect` runs on)."""
        opts = self.options
        depth = self._depth if depth is None else depth
        k = self._camera_k if k is None else k
        c = ppf.depth_counts(
            prep.samples * scale, prep.normals, cfo[None], depth, near_roi.reshape(depth.shape), k,
            opts.explain_tol_m, opts.noise_per_m2,
        )[0]  # fmt: skip
        return float(c[1]) / max(int(c[3]), 1)

    def _sinks(self, prep: PreparedTemplate, cfo: FloatArray) -> bool:
        """Whether the posed template reaches more than `max_sink_m` (plus 2.5 x the depth noise at its range) below
        the support plane: a part cannot lie in the floor. (A puck sunk 7 mm into the floor explains a 3 mm plate's
        top face; a profile sunk into it explains a plate.)"""
        if self._plane_c is None or self.options.max_sink_m <= 0:
            return False
        n, d = self._plane_c[:3], self._plane_c[3]
        r = cfo[:3, :3].T @ n  # heights of the object-frame samples: (R p + t) . n + d
        low = float(np.min(prep.samples @ r)) + float(cfo[:3, 3] @ n) + d
        z = float(cfo[2, 3])
        return low < -(self.options.max_sink_m + 2.5 * self.options.noise_per_m2 * z * z)

    def _evidence(self, prep: PreparedTemplate, cfo: FloatArray) -> float:
        """Depth-image evidence of a pose in [0, 1] (0: implausible): the share of its camera-visible, unoccluded
        surface that measured depth supports, minus 3 x the share the sensor saw through (free space); below
        `min_support` support or above `max_see_through` see-through it is 0."""
        opts = self.options
        k = self._camera_k
        pv, nv = kernels.visible_points(prep.samples, prep.normals, np.ascontiguousarray(cfo), 1.0, prep.spacing)
        if len(pv) == 0:
            return 0.0
        uv = kernels.project_pinhole(pv, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        tol = opts.explain_tol_m + 2.5 * opts.noise_per_m2 * float(np.median(pv[:, 2])) ** 2
        sup, den, vio, _mis, ng, _occ = kernels.depth_evidence(pv, nv, uv, self._depth, tol, 1)
        support = sup / max(den, 1)
        see = vio / max(ng, 1)
        if support < opts.min_support or see > opts.max_see_through or den < 0.3 * len(pv):
            return 0.0
        return float(max(support - 3.0 * see, 0.0))

    def _explained(
        self,
        pmap: FloatArray,
        allowed: BoolArray,
        prep: PreparedTemplate,
        cfo: FloatArray,
        scale: float,
        band_m: float = 0.0,
    ) -> IntArray:
        """Flat indices of `allowed` pixels whose point lies within the explain tolerance (plus `band_m` metres)
        of the posed model."""
        opts = self.options
        h, w = pmap.shape[:2]
        c = cfo[:3, :3] @ (prep.centroid * scale) + cfo[:3, 3]
        r = 0.5 * prep.diameter * scale * 1.1 + 0.005
        if c[2] <= r * 0.5:
            return np.zeros(0, dtype=np.int64)
        # the sphere's pixel box (pinhole; distortion is small next to the margin)
        k = self._camera_k
        u0 = int(np.floor(k[0, 0] * (c[0] - r) / max(c[2] - r, 1e-3) + k[0, 2])) - 2
        u1 = int(np.ceil(k[0, 0] * (c[0] + r) / max(c[2] - r, 1e-3) + k[0, 2])) + 2
        v0 = int(np.floor(k[1, 1] * (c[1] - r) / max(c[2] - r, 1e-3) + k[1, 2])) - 2
        v1 = int(np.ceil(k[1, 1] * (c[1] + r) / max(c[2] - r, 1e-3) + k[1, 2])) + 2
        u0, u1, v0, v1 = max(u0, 0), min(u1, w), max(v0, 0), min(v1, h)
        if u1 <= u0 or v1 <= v0:
            return np.zeros(0, dtype=np.int64)
        # compiled (ppf.explained_pixels): the exact nearest sample of each allowed pixel's point in the box
        return ppf.explained_pixels(
            pmap,
            allowed.reshape(h, w),
            (v0, v1, u0, u1),
            invert_pose(cfo),
            scale,
            prep,
            r / scale,
            0.05 * prep.diameter + 0.01 + band_m,
            opts.explain_tol_m + band_m,
            opts.noise_per_m2,
        )

    # -- output ---------------------------------------------------------------------------------
    def _instances(
        self, frame: RGBDFrame, accepted: list[tuple[_Hyp, TemplateFit]], mopts: MeasureOptions
    ) -> tuple[list[Instance], list[NormPosition], list[TemplateFit]]:
        from normpos_grasp.camera.render import render

        if not accepted:
            return [], [], []
        cam = frame.camera
        depth = np.asarray(frame.depth_m, dtype=np.float64)
        posed = [(hy.template.mesh.copy().apply_scale(f.scale), hy.camera_from_object) for hy, f in accepted]
        rend = render(cam, posed)
        agree = np.abs(depth - rend.depth_m) < self.options.explain_tol_m * 3 + 2.5 * self.options.noise_per_m2 * (
            depth**2
        )
        instances: list[Instance] = []
        fits: list[TemplateFit] = []
        for k, (hy, f) in enumerate(accepted):
            mask = (rend.index == k) & agree & (depth > 0)
            if mask.sum() < 3:
                mask = np.zeros(depth.shape, dtype=bool)
                mask.reshape(-1)[hy.pixels] = True
            iid = len(instances) + 1
            instances.append(Instance(mask, hy.template.label, float(np.clip(f.score, 0.0, 1.0)), iid))
            fits.append(replace(f, instance_id=iid, extra={**f.extra, "detector": "cad", "ppf_votes": hy.votes}))
        nps = measure_instances(frame, instances, mopts)
        have = {n.instance_id for n in nps}
        keep = [i for i, inst in enumerate(instances) if inst.instance_id in have]
        return [instances[i] for i in keep], nps, [fits[i] for i in keep]


def _is_flat(prep: PreparedTemplate) -> bool:
    """Whether the template is a plate: its thinnest principal extent under 12 % of its diameter."""
    q = prep.samples - prep.samples.mean(axis=0)
    _, _, vt = np.linalg.svd(q[:: max(1, len(q) // 1000)], full_matrices=False)
    ext = np.ptp(q @ vt.T, axis=0)
    return bool(ext.min() < 0.12 * prep.diameter)


def _turned(cfo: FloatArray, axis: FloatArray, centre: FloatArray, angle: float) -> FloatArray:
    """cfo turned by `angle` radians about the camera-frame `axis` (unit, (3,)) through the camera-frame `centre`."""
    kx = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    r = np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = centre - r @ centre
    return np.asarray(t @ cfo, dtype=np.float64)


def _stack(poses: list[FloatArray]) -> FloatArray:
    return np.stack(poses) if poses else np.zeros((0, 4, 4))


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def _prescore(
    prep: PreparedTemplate, poses: FloatArray, sp: FloatArray, tol_m: float, noise_per_m2: float, n_keep: int
) -> IntArray:
    """Indices of the (at most `n_keep`) voted poses explaining the most downsampled scene points (within tol of
    the model surface, distance-grid lookup), those explaining under half the best one's dropped."""
    if len(poses) == 0:
        return np.zeros(0, dtype=np.int64)
    ofc = np.linalg.inv(poses)
    po = np.einsum("kij,vj->kvi", ofc[:, :3, :3], sp) + ofc[:, None, :3, 3]
    flat = po.reshape(-1, 3)
    idx, inside = prep.grid_lookup(flat)
    d = np.linalg.norm(flat - prep.samples[idx], axis=1).reshape(len(poses), -1)
    tol = tol_m + 2.5 * noise_per_m2 * sp[:, 2] ** 2 + 0.5 * prep.grid_cell
    count = ((d < tol[None, :]) & (inside.reshape(len(poses), -1) > 0)).sum(axis=1)
    order = np.argsort(-count, kind="stable")[:n_keep]
    return order[count[order] >= 0.5 * count[order[0]]]


def _thin_above(height: FloatArray, low: BoolArray, opts: CadOptions) -> BoolArray:
    """(H, W) pixels of thin parts lying on the support plane: among the `low` pixels (within the plane band; (H *
    W,)), those whose height over the plane (`height`, (H, W) metres), averaged over the low pixels of a
    `thin_window_px` window, exceeds `thin_above_m` or 2.5 x the spread of those means (a plane that is not
    flat in the frame keeps nothing). A 3 mm plate on the floor lies inside the per-pixel band (2.5 x
    the noise is 5-7 mm at 0.7-0.9 m) but its window mean stands clear of the floor's; tall parts are left out of
    the mean (they are kept by the band), so the floor beside them stays out."""
    import cv2

    if opts.thin_above_m <= 0:
        return np.zeros(height.shape, dtype=bool)
    k = (opts.thin_window_px, opts.thin_window_px)
    lo = low.reshape(height.shape)
    num = cv2.boxFilter(np.where(lo, height, 0.0), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(lo.astype(np.float64), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    mean = num / np.maximum(den, 1.0)
    full = lo & (den >= 0.5 * k[0] * k[1])
    if not full.any():
        return np.zeros(height.shape, dtype=bool)
    # the plane's own flatness sets the floor: 2.5 x the spread of the window means over the band (on a
    # simulated bin floor well under a millimetre; on the real LM-O table, whose plane comes from one part's ground
    # truth, +-6 mm: there the rule keeps nothing rather than the table)
    m = mean[full]
    # from the lower quartile only (a normal's 2.5 to 25 % quantiles are 1.29 sigma apart): thin parts lift the
    # median and the upper tail, the floor's noise is on both sides
    lo_q, mid_q = np.percentile(m, [2.5, 25.0])
    spread = float(mid_q - lo_q) / 1.286
    thr = max(opts.thin_above_m, 2.5 * spread)
    thin = full & (mean > thr) & (height > 0.0)
    # the window mean erodes a plate's outline (its edge windows half on the floor): grow it back by 2 pixels over
    # the in-band pixels above the plane (on a 3 mm plate at 0.8 m: 71 % of its pixels kept without, 95 % with)
    return np.asarray(_dilate(thin, 2) & lo & (height > 0.0))


def _dilate(mask: BoolArray, px: int) -> BoolArray:
    import cv2

    if px <= 0 or not mask.any():
        return mask
    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return np.asarray(cv2.dilate(mask.view(np.uint8), k) > 0)


def _downsample(pts: FloatArray, pix: IntArray, step: float) -> tuple[FloatArray, FloatArray, IntArray]:
    """Voxel means of (N, 3) points at `step` metres: points (V, 3), normals (V, 3) towards the camera at the
    origin, and one pixel index per voxel (its first point's)."""
    key = np.floor(pts / step).astype(np.int64)
    _, first, inv, cnt = np.unique(key, axis=0, return_index=True, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    mean = np.stack([np.bincount(inv, weights=pts[:, i]) for i in range(3)], axis=1) / cnt[:, None]
    keep = cnt >= 2  # single stray pixels (flying pixels at edges) carry no surface
    mean, first = mean[keep], first[keep]
    if len(mean) < 10:
        return mean, np.zeros_like(mean), pix[first]
    nrm = estimate_normals(mean, np.zeros(3), k=10)
    return mean, nrm, pix[first]


def _dominant_plane(pts: FloatArray, band: FloatArray, iterations: int = 150) -> FloatArray | None:
    """(4,) camera-frame plane with the most points within `band` (seeded RANSAC on a subsample), or None."""
    if len(pts) < 100:
        return None
    rng = np.random.default_rng(0)
    sub = rng.choice(len(pts), size=min(len(pts), 4000), replace=False)
    p, b = pts[sub], band[sub]
    best, best_n = None, 0
    for _ in range(iterations):
        tri = p[rng.choice(len(p), 3, replace=False)]
        n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        ln = float(np.linalg.norm(n))
        if ln < 1e-12:
            continue
        n /= ln
        d = -float(n @ tri[0])
        k = int((np.abs(p @ n + d) < b).sum())
        if k > best_n:
            best, best_n = np.concatenate([n, [d]]), k
    if best is None or best_n < 0.2 * len(p):
        return None
    return best
