"""End-to-end perception benchmark: segment -> measure -> fit on held-out synthetic bin scenes, per segmenter.

Scenes: the packaged cell 'ur5e_bin_parallel' (normpos_grasp.demo.resolve_cell) filled with `--parts` parts by
normpos_grasp.sim.cell_scene.compose_cell_scene (physics-settled), seen by the cell's fixed camera (about 0.88 m
above the bin floor, looking down) at 640x480 with the D435 sensor model. Each frame goes through
normpos_grasp.pipeline.perceive with every segmenter of `--segmenters`: 'model' (the bundled ONNX model,
skipped with a note when it is not packaged), 'depth' (the model-free depth segmenter) and 'gt' (the frame's true
visible masks, SyntheticFrame.instances: everything after segmentation on its own).

Protocol (per object):
- eligible: >= 400 visible pixels and visible fraction >= 0.3;
- detected: an instance matches it at mask IoU >= 0.5 (one-to-one, greedy by IoU);
- class: the segmenter's label, or for unlabelled instances (depth segmenter) the accepted fit's template
  label ('' when no fit was accepted, which counts as wrong); accuracy over detected objects;
- accepted: the matched instance's fit was accepted; translation error: area centroid of the fitted template
  vs the true one; rotation error and ADD(-S): minimum over the template's symmetry transforms
  (Symmetry.transforms, continuous axes every 1 degree); correct pose: same template and ADD(-S) < 0.1 d;
- wrong accepted: every accepted fit of the frame (also on instances that match no eligible object; those are
  scored against the part they overlap most) with a wrong template or ADD(-S) >= 0.1 d, as a share of accepted fits;
- centroid error: the norm-position's centroid vs the centroid of the true visible surface (ideal depth of the
  true visible mask, back-projected), the paper's kind of 3D position error;
- times: median over frames of perceive's 'segment', 'measure', 'fit' wall times and their sum, ms (CPU only).

    nice -n 10 .venv/bin/python benchmarks/bench_pipeline.py [--scenes 25] [--parts 8] [--seed 9100]
        [--segmenters model,depth,gt] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from normpos_grasp.errors import NormposError
from normpos_grasp.geometry.transforms import rotation_angle
from normpos_grasp.records.template import Template
from normpos_grasp.templates.prepared import prepare

PAPER = "paper (YOLACT, ZED2): detection 96.5 % (193/200), 55 ms/frame on an RTX 2080 Ti, 3D position error 22.75 cm"
MIN_VISIBLE_PX = 400
MIN_VISIB_FRACT = 0.3
MATCH_IOU = 0.5


@dataclass
class Tally:
    """What one segmenter did over all frames."""

    eligible: int = 0
    detected: int = 0
    class_ok: int = 0
    accepted: int = 0
    correct: int = 0  # accepted with the right template and ADD(-S) < 0.1 d (eligible objects)
    accepted_all: int = 0  # every accepted fit of every frame
    wrong_all: int = 0  # accepted fits with a wrong template or ADD(-S) >= 0.1 d
    instances: int = 0
    unmatched: int = 0  # instances matching no true part at IoU >= 0.5
    trans_mm: list[float] = field(default_factory=list)
    rot_deg: list[float] = field(default_factory=list)
    centroid_mm: list[float] = field(default_factory=list)
    times: dict[str, list[float]] = field(default_factory=dict)
    frames: int = 0
    objects: int = 0  # true parts in the frames (any visibility)
    wrong_kinds: Counter[str] = field(default_factory=Counter)  # 'truth->fit' of wrong accepted fits


def pose_errors(template: Template, est: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    """(translation error m, rotation error deg, ADD(-S) m) of `est` vs `gt` (4, 4), symmetry-aware."""
    prep = prepare(template)
    c = prep.centroid
    trans = float(np.linalg.norm((est[:3, :3] @ c + est[:3, 3]) - (gt[:3, :3] @ c + gt[:3, 3])))
    if len(template.symmetry.continuous) >= 2:  # sphere-like: only the centre is defined
        _, pt = template.symmetry.continuous[0]
        d = float(np.linalg.norm((est[:3, :3] @ pt + est[:3, 3]) - (gt[:3, :3] @ pt + gt[:3, 3])))
        return trans, 0.0, d
    sub = prep.samples[::4]
    syms = template.symmetry.transforms(continuous_steps=360)
    pe = sub @ est[:3, :3].T + est[:3, 3]
    best_add, best_rot = np.inf, np.inf
    for s in syms:
        g = gt @ s
        add = float(np.mean(np.linalg.norm(pe - (sub @ g[:3, :3].T + g[:3, 3]), axis=1)))
        if add < best_add:
            best_add, best_rot = add, float(np.degrees(rotation_angle(g[:3, :3].T @ est[:3, :3])))
    return trans, best_rot, best_add


def match(masks: list[np.ndarray], instance_ids: np.ndarray, visible_px: np.ndarray) -> tuple[dict[int, int], list]:
    """Greedy one-to-one matching of instance masks to true parts at IoU >= MATCH_IOU.

    Returns ({instance index: part index}, per instance (part with the largest IoU or -1, that IoU)).
    """
    n_parts = len(visible_px)
    pairs = []
    best = []
    for i, m in enumerate(masks):
        inter = np.bincount(instance_ids[m].ravel(), minlength=n_parts + 1)[1 : n_parts + 1]
        union = m.sum() + visible_px - inter
        iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
        k = int(np.argmax(iou)) if n_parts else -1
        best.append((k if n_parts and iou[k] > 0 else -1, float(iou[k]) if n_parts else 0.0))
        pairs += [(float(iou[j]), i, j) for j in np.flatnonzero(iou >= MATCH_IOU)]
    out: dict[int, int] = {}
    used: set[int] = set()
    for _, i, j in sorted(pairs, reverse=True):
        if i not in out and j not in used:
            out[i] = int(j)
            used.add(int(j))
    return out, best


def true_visible_centroids(sf: Any) -> np.ndarray:
    """(N, 3) world centroid of each part's true visible surface (ideal depth), NaN where nothing is visible."""
    cam = sf.frame.camera
    depth = sf.rendering.depth_m
    out = np.full((len(sf.layout.templates), 3), np.nan)
    for k, m in enumerate(sf.rendering.masks_visible):
        sel = m & (depth > 0)
        if sel.any():
            v, u = np.nonzero(sel)
            out[k] = cam.backproject_to_world(np.column_stack([u, v]), depth[v, u]).mean(axis=0)
    return out


def score_frame(sf: Any, result: Any, tally: Tally, diameters: dict[str, float]) -> None:
    """Add one frame's objects and fits to `tally`."""
    templates = sf.layout.templates
    visible_px = sf.rendering.masks_visible.reshape(len(templates), -1).sum(axis=1)
    eligible = (visible_px >= MIN_VISIBLE_PX) & (sf.visib_fractions >= MIN_VISIB_FRACT)
    instances = result.instances
    matched, best = match([i.mask for i in instances], sf.rendering.instance_ids, visible_px)
    by_id = {n.instance_id: (n, f) for n, f in zip(result.normpositions, result.fits, strict=True)}
    truth_centroids = true_visible_centroids(sf)
    cam = sf.frame.camera
    tally.frames += 1
    tally.objects += len(templates)
    tally.instances += len(instances)
    tally.unmatched += len(instances) - len(matched)
    tally.eligible += int(eligible.sum())
    for i, inst in enumerate(instances):
        npos, fit = by_id.get(inst.instance_id, (None, None))
        part = matched.get(i, best[i][0])
        if fit is not None and fit.accepted:
            tally.accepted_all += 1
            ok = part >= 0 and fit.template.name == templates[part].name
            if ok:
                _, _, add = pose_errors(
                    templates[part], _world(fit.frame_from_object, fit.frame, cam), sf.world_from_object[part]
                )
                ok = add < 0.1 * diameters[templates[part].name]
            tally.wrong_all += int(not ok)
            if not ok:
                truth = templates[part].name if part >= 0 else "nothing"
                tally.wrong_kinds[f"{truth}->{fit.template.name}"] += 1
        if i not in matched or not eligible[part]:
            continue
        tally.detected += 1
        label = inst.label or (fit.template.label if fit is not None and fit.accepted else "")
        tally.class_ok += int(label == templates[part].label)
        if npos is not None:
            c = npos.centroid if npos.frame == "world" else _world_point(npos.centroid, cam)
            tally.centroid_mm.append(float(np.linalg.norm(c - truth_centroids[part])) * 1e3)
        if fit is None or not fit.accepted:
            continue
        tally.accepted += 1
        est = _world(fit.frame_from_object, fit.frame, cam)
        if fit.template.name != templates[part].name:
            c_est = est[:3, :3] @ prepare(fit.template).centroid + est[:3, 3]
            gt = sf.world_from_object[part]
            c_gt = gt[:3, :3] @ prepare(templates[part]).centroid + gt[:3, 3]
            tally.trans_mm.append(float(np.linalg.norm(c_est - c_gt)) * 1e3)
            continue
        trans, rot, add = pose_errors(templates[part], est, sf.world_from_object[part])
        tally.trans_mm.append(trans * 1e3)
        tally.rot_deg.append(rot)
        tally.correct += int(add < 0.1 * diameters[templates[part].name])
    for key, ms in result.timings_ms.items():
        tally.times.setdefault(key, []).append(ms)
    tally.times.setdefault("total", []).append(sum(result.timings_ms.values()))


def _world(pose: np.ndarray, frame: str, cam: Any) -> np.ndarray:
    return pose if frame == "world" else cam.require_world_from_camera() @ pose


def _world_point(p: np.ndarray, cam: Any) -> np.ndarray:
    t = cam.require_world_from_camera()
    return t[:3, :3] @ p + t[:3, 3]


def _pct(a: int, b: int) -> str:
    return f"{100.0 * a / b:.1f} % ({a}/{b})" if b else "-"


def _q(values: list[float], q: float) -> str:
    return f"{np.percentile(values, q):.1f}" if values else "-"


def summary(t: Tally) -> dict[str, Any]:
    """Figures of one tally (JSON-ready)."""
    med = {k: float(np.median(v)) for k, v in t.times.items()}
    return {
        "frames": t.frames,
        "eligible": t.eligible,
        "detected": t.detected,
        "class_ok": t.class_ok,
        "accepted": t.accepted,
        "correct": t.correct,
        "accepted_all": t.accepted_all,
        "wrong_all": t.wrong_all,
        "instances": t.instances,
        "unmatched": t.unmatched,
        "trans_mm_median": float(np.median(t.trans_mm)) if t.trans_mm else None,
        "trans_mm_p90": float(np.percentile(t.trans_mm, 90)) if t.trans_mm else None,
        "rot_deg_median": float(np.median(t.rot_deg)) if t.rot_deg else None,
        "rot_deg_p90": float(np.percentile(t.rot_deg, 90)) if t.rot_deg else None,
        "centroid_mm_median": float(np.median(t.centroid_mm)) if t.centroid_mm else None,
        "centroid_mm_p90": float(np.percentile(t.centroid_mm, 90)) if t.centroid_mm else None,
        "time_ms_median": med,
        "wrong_kinds": dict(t.wrong_kinds),
    }


def table(tallies: dict[str, Tally]) -> str:
    names = list(tallies)
    rows: list[tuple[str, list[str]]] = []

    def row(label: str, fn: Any) -> None:
        rows.append((label, [fn(tallies[n]) for n in names]))

    row("objects / eligible", lambda t: f"{t.objects} / {t.eligible}")
    row("detection (IoU >= 0.5)", lambda t: _pct(t.detected, t.eligible))
    row("class accuracy (detected)", lambda t: _pct(t.class_ok, t.detected))
    row("accepted fit (eligible)", lambda t: _pct(t.accepted, t.eligible))
    row("ADD(-S) < 0.1 d recall", lambda t: _pct(t.correct, t.eligible))
    row("wrong among accepted", lambda t: _pct(t.wrong_all, t.accepted_all))
    row("translation mm med / p90", lambda t: f"{_q(t.trans_mm, 50)} / {_q(t.trans_mm, 90)}")
    row("rotation deg med / p90", lambda t: f"{_q(t.rot_deg, 50)} / {_q(t.rot_deg, 90)}")
    row("centroid err mm med / p90", lambda t: f"{_q(t.centroid_mm, 50)} / {_q(t.centroid_mm, 90)}")
    row("instances / unmatched", lambda t: f"{t.instances} / {t.unmatched}")
    for key in ("segment", "measure", "fit", "total"):
        row(f"{key} ms/frame (median)", lambda t, k=key: _q(t.times.get(k, []), 50))
    w0 = max(len(r[0]) for r in rows)
    ws = [max(len(n), *(len(r[1][i]) for r in rows)) for i, n in enumerate(names)]
    lines = ["  ".join([" " * w0] + [n.rjust(w) for n, w in zip(names, ws, strict=True)])]
    lines += ["  ".join([lab.ljust(w0)] + [v.rjust(w) for v, w in zip(vals, ws, strict=True)]) for lab, vals in rows]
    return "\n".join(lines)


def comparison(tallies: dict[str, Tally]) -> str:
    parts = []
    for name, t in tallies.items():
        seg = _q(t.times.get("segment", []), 50)
        tot = _q(t.times.get("total", []), 50)
        cen = f"{np.median(t.centroid_mm) / 10:.2f}" if t.centroid_mm else "-"
        tr = f"{np.median(t.trans_mm) / 10:.2f}" if t.trans_mm else "-"
        det = f"{100.0 * t.detected / t.eligible:.1f}" if t.eligible else "-"
        parts.append(f"{name}: det {det} %, segment {seg} / total {tot} ms, centroid {cen} cm, fit {tr} cm")
    return f"vs {PAPER} | here (CPU): " + "; ".join(parts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=25, help="scenes (one frame each)")
    ap.add_argument("--parts", type=int, default=8, help="parts dropped into the bin per scene")
    ap.add_argument("--seed", type=int, default=9100, help="scene i uses seed + i (layout and sensor noise)")
    ap.add_argument("--segmenters", default="model,depth,gt", help="comma list of model, depth, gt")
    ap.add_argument("--cell", default="ur5e_bin_parallel", help="packaged cell name or cell YAML")
    ap.add_argument("--json", default="", help="also write the figures to this JSON file")
    args = ap.parse_args()

    from normpos_grasp.cell import resolve_cell
    from normpos_grasp.pipeline import make_segmenter, perceive
    from normpos_grasp.sim.cell_scene import cell_camera, compose_cell_scene
    from normpos_grasp.sim.dataset import render_frame
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.sim.render import make_renderer
    from normpos_grasp.sim.sensor import sensor_preset

    cell = resolve_cell(args.cell)
    library = default_part_library()
    diameters = {t.name: prepare(t).diameter for t in library}
    camera = cell_camera(cell, "d435", (640, 480))
    sensor = sensor_preset("d435")
    segmenters: dict[str, Any] = {}
    for kind in [s.strip() for s in args.segmenters.split(",") if s.strip()]:
        if kind == "gt":
            segmenters[kind] = None
            continue
        try:
            segmenters[kind] = make_segmenter(kind)
        except NormposError as exc:
            print(f"segmenter {kind!r} skipped: {exc}")
    tallies = {k: Tally() for k in segmenters}
    t_start = time.perf_counter()
    t_scene = 0.0
    for i in range(args.scenes):
        t0 = time.perf_counter()
        layout = compose_cell_scene(cell, args.parts, args.seed + i, library)
        renderer = make_renderer(layout, camera.width, camera.height)
        try:
            sf = render_frame(layout, renderer, camera, sensor, np.random.default_rng(args.seed + i), scene_id=i)
        finally:
            renderer.close()
        t_scene += time.perf_counter() - t0
        for kind, seg in segmenters.items():
            gt = sf.instances if kind == "gt" else None
            result = perceive(sf.frame, seg if seg is not None else _NoSegmenter(), library, instances=gt)
            score_frame(sf, result, tallies[kind], diameters)
        print(f"scene {i + 1}/{args.scenes} done, {time.perf_counter() - t_start:.0f} s", file=sys.stderr, flush=True)
    n_obj = sum(len(t.trans_mm) for t in tallies.values())
    print(
        f"{args.scenes} scenes x {args.parts} parts, cell {cell.name}, D435 noise, {camera.width}x{camera.height}, "
        f"seeds {args.seed}..{args.seed + args.scenes - 1}; scene generation {t_scene:.0f} s, "
        f"wall {time.perf_counter() - t_start:.0f} s ({n_obj} accepted fits scored)"
    )
    print(table(tallies))
    for kind, t in tallies.items():
        if t.wrong_kinds:
            kinds = ", ".join(f"{k} x{n}" for k, n in t.wrong_kinds.most_common())
            print(f"{kind}: wrong accepted (truth->fit): {kinds}")
    print(comparison(tallies))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({k: summary(t) for k, t in tallies.items()}, fh, indent=2)
    return 0


class _NoSegmenter:
    """Stands in for a segmenter when perceive() gets the true instances."""

    def segment(self, frame: Any) -> list[Any]:
        raise NormposError("the ground-truth run passes instances; segment() must not be called")


if __name__ == "__main__":
    raise SystemExit(main())
