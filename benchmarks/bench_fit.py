"""Template pose-fitting benchmark on synthetic bin scenes (D435 noise, camera 0.5-1.0 m).

Scenes: normpos_grasp.sim.dataset.generate_frame (physics-settled parts in a bin, ray-cast, D435 sensor
model); masks: ground-truth visible masks; norm-positions: normpos_grasp.measure.measure.measure_instances;
fit: normpos_grasp.templates.fit.fit_template with the frame's depth image as FitContext. Objects with a
visible fraction < 0.3 are skipped (the issue's protocol). Errors are symmetry-aware: the template's symmetry
transforms (continuous axes sampled every 1 degree) are searched for the closest equivalent GT pose.
Timing: CPU time (process_time) per object of sequential `fit_template` calls, and the wall time of
`fit_many` (threads, --workers) over each frame's objects scaled to 10 objects, median over --repeats;
both after a warm-up fit, whose time (compiled-kernel load, or compile on a fresh install) is printed apart.

    .venv/bin/python benchmarks/bench_fit.py [--frames 12] [--seed 1] [--unlabelled 4] [--lmo] [--workers 2]

`--gil-share` measures instead what two threads can gain (issue 21 item 2), in thread CPU time, which another
process's load does not change: every call of a compiled kernel (`templates.kernels`, numba) made from the fitting
modules is timed with `time.thread_time` around it, and the kernels' share of each `fit_best`'s thread CPU is the
part that runs without the GIL (kernels compiled without nogil are counted apart). Amdahl's bound for 2 threads,
1 / ((1 - share) + share / 2), caps `fit_many`'s gain from its GIL-free part (numpy and scipy release the GIL in
some of their own loops too: the bound is a floor of what could run in parallel, the wall ratio its outcome). Also
printed: the process CPU and the wall of `fit_many` with 1 and 2 workers on the same objects, with the load.

    nice -n 10 .venv/bin/python benchmarks/bench_fit.py --gil-share --frames 4
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.geometry.transforms import rotation_angle
from normpos_grasp.records.template import Template
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_best, fit_many, fit_template
from normpos_grasp.templates.prepared import prepare


def sym_errors(template: Template, est: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    """(translation error m, rotation error deg, ADD(-S) m): min over symmetric GT equivalents."""
    prep = prepare(template)
    if len(template.symmetry.continuous) >= 2:  # fully rotation-symmetric (sphere): only the centre matters
        _, pt = template.symmetry.continuous[0]
        d = float(np.linalg.norm((est[:3, :3] @ pt + est[:3, 3]) - (gt[:3, :3] @ pt + gt[:3, 3])))
        return d, 0.0, d
    sub = prep.samples[::4]
    syms = template.symmetry.transforms(continuous_steps=360 if len(template.symmetry.continuous) == 1 else 72)
    pe = sub @ est[:3, :3].T + est[:3, 3]
    best = (np.inf, np.inf, np.inf)
    for s in syms:
        g = gt @ s
        add = float(np.mean(np.linalg.norm(pe - (sub @ g[:3, :3].T + g[:3, 3]), axis=1)))
        if add < best[2]:
            best = (
                float(np.linalg.norm(est[:3, 3] - g[:3, 3])),
                float(np.degrees(rotation_angle(g[:3, :3].T @ est[:3, :3]))),
                add,
            )
    # translation of the object centre (origin may sit off-centre): use the area centroid
    c = prep.centroid
    tc = float(np.linalg.norm((est[:3, :3] @ c + est[:3, 3]) - (gt[:3, :3] @ c + gt[:3, 3])))
    return tc, best[1], best[2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--count", type=int, default=10, help="parts per scene")
    ap.add_argument("--unlabelled", type=int, default=3, help="frames also run with label '' (fit_best)")
    ap.add_argument("--lmo", action="store_true", help="also fit the LM-O real frame (../shared/data)")
    ap.add_argument("--workers", type=int, default=2, help="threads of fit_many")
    ap.add_argument("--repeats", type=int, default=3, help="fit_many timing repeats per frame")
    ap.add_argument("--gil-share", action="store_true", help="measure the GIL-free share of fit CPU and stop")
    args = ap.parse_args()
    if args.gil_share:
        gil_share(args.frames, args.seed, args.count, args.repeats)
        return

    from normpos_grasp.measure.measure import measure_instances
    from normpos_grasp.sim.cameras import CameraOptions
    from normpos_grasp.sim.dataset import generate_frame
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.sim.scene import SceneOptions

    library = default_part_library()
    print(f"load average before: {_load()} (1 / 5 / 15 min, {os.cpu_count()} CPUs)")
    t_prep = time.perf_counter()
    for t in library:
        prepare(t)
    t_prep = time.perf_counter() - t_prep
    opts = FitOptions()
    t_first = -1.0
    many_wall: list[float] = []
    many_same = True
    rows = []
    cpu_times: list[float] = []
    unl_cpu: list[float] = []
    unl = [0, 0, 0]
    t_gen = 0.0
    for f in range(args.frames):
        t0 = time.perf_counter()
        sf = generate_frame(
            SceneOptions(count=args.count, seed=args.seed * 1000 + f),
            "d435",
            CameraOptions(distance_m=(0.5, 1.0)),
            seed=args.seed * 7919 + f,
            library=library,
        )
        insts = [i for i in sf.instances if sf.visib_fractions[i.source_id] >= 0.3]
        nps = measure_instances(sf.frame, insts)
        t_gen += time.perf_counter() - t0
        ctx = FitContext(sf.frame.camera, sf.frame.depth_m)
        if t_first < 0 and nps:  # warm-up: loads (or, on a fresh install, compiles) the fitting kernels
            w0 = time.perf_counter()
            fit_template(nps[0], sf.layout.templates[insts[0].source_id], opts, ctx)
            t_first = time.perf_counter() - w0
        fits = []
        for n, i in zip(nps, insts, strict=True):
            c0 = time.process_time()
            fits.append(fit_template(n, sf.layout.templates[i.source_id], opts, ctx))
            cpu_times.append(time.process_time() - c0)
        if nps:
            reps = []
            for _ in range(args.repeats):
                w0 = time.perf_counter()
                many = fit_many(nps, library, opts, ctx, workers=args.workers)
                reps.append((time.perf_counter() - w0) / len(nps) * 10)
            many_wall.append(float(np.median(reps)))
            many_same &= all(
                m.accepted == f.accepted and np.allclose(m.frame_from_object, f.frame_from_object, atol=1e-9)
                for m, f in zip(many, fits, strict=True)
            )
        for fit, inst in zip(fits, insts, strict=True):
            t = sf.layout.templates[inst.source_id]
            gt = sf.world_from_object[inst.source_id]
            te, re, add = sym_errors(t, fit.frame_from_object, gt)
            correct = add < 0.1 * prepare(t).diameter
            rows.append((t.name, te, re, add, correct, fit.accepted, fit.time_s, fit.scale))
        if f < args.unlabelled:
            from dataclasses import replace

            for n, inst in zip(nps, insts, strict=True):
                c0 = time.process_time()
                fb = fit_best(replace(n, label=""), library, opts, ctx)
                unl_cpu.append(time.process_time() - c0)
                t = sf.layout.templates[inst.source_id]
                unl[0] += 1
                unl[1] += int(fb.accepted and fb.template.name == t.name)
                unl[2] += int(fb.accepted and fb.template.name != t.name)
    a = np.array([r[1:] for r in rows], dtype=float)
    names = sorted({r[0] for r in rows})
    acc = a[:, 4] == 1
    print(f"objects: {len(rows)} in {args.frames} frames (visible fraction >= 0.3), scene generation {t_gen:.1f} s")
    print(
        f"median translation error {np.median(a[:, 0]) * 1000:.2f} mm, "
        + f"median rotation error {np.median(a[:, 1]):.2f} deg"
    )
    print(
        f"ADD(-S) < 0.1 d recall (all fits): {a[:, 3].mean():.3f}; accepted: {acc.mean():.3f}; "
        f"recall of accepted-and-correct: {(acc & (a[:, 3] == 1)).mean():.3f}"
    )
    wrong = int((acc & (a[:, 3] == 0)).sum())
    print(f"accepted wrong poses: {wrong} of {int(acc.sum())} accepted ({100 * wrong / max(acc.sum(), 1):.2f} %)")
    if acc.any():
        print(f"accepted fits: median {np.median(a[acc, 0]) * 1000:.2f} mm / {np.median(a[acc, 1]):.2f} deg")
    print(
        f"first fit (kernel load; a compile on a fresh install): {t_first:.2f} s; template preparation "
        f"{t_prep / len(library) * 1000:.0f} ms per template"
    )
    print(f"time per object: median {np.median(a[:, 5]) * 1000:.1f} ms, p90 {np.percentile(a[:, 5], 90) * 1000:.1f} ms")
    print(
        f"CPU time (process_time) per object: median {np.median(cpu_times) * 1000:.1f} ms, "
        f"p90 {np.percentile(cpu_times, 90) * 1000:.1f} ms"
    )
    print(
        f"fit_many wall time per 10 objects ({args.workers} workers, median of {args.repeats} repeats per frame): "
        f"median {np.median(many_wall) * 1000:.0f} ms, p90 {np.percentile(many_wall, 90) * 1000:.0f} ms "
        f"(results equal to fit_template: {many_same})"
    )
    print(f"size factor: median {np.median(a[:, 6]):.4f}, p90 |s-1| {np.percentile(np.abs(a[:, 6] - 1), 90):.4f}")
    for name in names:
        sel = np.array([r[0] == name for r in rows])
        print(
            f"  {name:9s} n={sel.sum():3d} med {np.median(a[sel, 0]) * 1000:5.2f} mm {np.median(a[sel, 1]):5.2f} deg "
            f"recall {a[sel, 3].mean():.2f} accepted {a[sel, 4].mean():.2f} wrong-accepted "
            f"{int((a[sel, 4] == 1).sum() - ((a[sel, 4] == 1) & (a[sel, 3] == 1)).sum())}"
        )
    if unl[0]:
        print(
            f"label '' (fit_best over {len(library)} templates): {unl[1]}/{unl[0]} right template accepted, "
            f"{unl[2]} wrong template accepted; CPU per object median {np.median(unl_cpu) * 1000:.0f} ms"
        )
    print(f"load average after: {_load()}")
    if args.lmo:
        lmo()


class _TimedKernels:
    """Stands in for the `kernels` module in the fitting modules: its compiled kernels timed per call (thread CPU)."""

    def __init__(self, module: Any) -> None:
        self.module = module
        self.seconds: Counter[str] = Counter()
        self.calls: Counter[str] = Counter()
        self.nogil: dict[str, bool] = {}
        self._wrapped: dict[str, Any] = {}

    def __getattr__(self, name: str) -> Any:
        value = getattr(self.module, name)
        if not hasattr(value, "targetoptions"):  # not a numba dispatcher: constants, Python helpers
            return value
        if name not in self._wrapped:
            self.nogil[name] = bool(value.targetoptions.get("nogil", False))

            def timed(*a: Any, _k: Any = value, _n: str = name) -> Any:
                t0 = time.thread_time()
                try:
                    return _k(*a)
                finally:
                    self.seconds[_n] += time.thread_time() - t0
                    self.calls[_n] += 1

            self._wrapped[name] = timed
        return self._wrapped[name]


def gil_share(frames: int, seed: int, count: int, repeats: int) -> None:
    """Print the share of fit thread CPU spent in GIL-free compiled kernels, and fit_many with 1 and 2 workers."""
    import importlib

    from normpos_grasp.measure.measure import measure_instances
    from normpos_grasp.sim.cameras import CameraOptions
    from normpos_grasp.sim.dataset import generate_frame
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.sim.scene import SceneOptions
    from normpos_grasp.templates import kernels

    library = default_part_library()
    for t in library:
        prepare(t)
    opts = FitOptions()
    print(f"load average before: {_load()} (1 / 5 / 15 min, {os.cpu_count()} CPUs)")
    cases = []
    for f in range(frames):
        sf = generate_frame(
            SceneOptions(count=count, seed=seed * 1000 + f),
            "d435",
            CameraOptions(distance_m=(0.5, 1.0)),
            seed=seed * 7919 + f,
            library=library,
        )
        insts = [i for i in sf.instances if sf.visib_fractions[i.source_id] >= 0.3]
        if insts:
            cases.append((measure_instances(sf.frame, insts), FitContext(sf.frame.camera, sf.frame.depth_m)))
    fit_best(cases[0][0][0], library, opts, cases[0][1])  # warm-up: kernels loaded (or compiled)
    timed = _TimedKernels(kernels)
    users = [
        importlib.import_module(f"normpos_grasp.templates.{m}")
        for m in ("fit", "icp", "scoring", "edges", "control_points", "features")
    ]
    for m in users:
        m.kernels = timed  # type: ignore[attr-defined]
    try:
        for _ in range(2):  # the first pass fills what the fitter caches on first use; the second is measured
            shares, totals = [], []
            timed.seconds.clear()
            timed.calls.clear()
            for nps, ctx in cases:
                for n in nps:
                    before = sum(timed.seconds.values())
                    t0 = time.thread_time()
                    fit_best(n, library, opts, ctx)
                    total = time.thread_time() - t0
                    totals.append(total)
                    shares.append((sum(timed.seconds.values()) - before) / total)
    finally:
        for m in users:
            m.kernels = kernels  # type: ignore[attr-defined]
    nogil_s = sum(v for k, v in timed.seconds.items() if timed.nogil[k])
    gil_s = sum(v for k, v in timed.seconds.items() if not timed.nogil[k])
    all_s = float(np.sum(totals))
    share = nogil_s / all_s
    n_obj = len(totals)
    per_obj = np.median(totals) * 1e3
    print(f"objects: {n_obj} in {len(cases)} frames; fit_best thread CPU per object median {per_obj:.1f} ms")
    print(
        f"in compiled nogil kernels: {100 * share:.1f} % of fit thread CPU (per object median "
        f"{100 * np.median(shares):.1f} %, p10 {100 * np.percentile(shares, 10):.1f} %); compiled with the GIL: "
        f"{100 * gil_s / all_s:.1f} %; {sum(timed.calls.values()) / n_obj:.0f} kernel calls per object"
    )
    print(f"Amdahl bound for 2 threads from the nogil share: {1 / ((1 - share) + share / 2):.2f}x")
    top = sorted(timed.seconds.items(), key=lambda kv: -kv[1])[:8]
    print("  kernels, ms per object: " + ", ".join(f"{k} {v / n_obj * 1e3:.1f}" for k, v in top))
    for workers in (1, 2, 1, 2):
        walls, cpus = [], []
        for nps, ctx in cases:
            for _ in range(repeats):
                w0, c0 = time.perf_counter(), time.process_time()
                fit_many(nps, library, opts, ctx, workers=workers)
                walls.append((time.perf_counter() - w0) / len(nps) * 10)
                cpus.append((time.process_time() - c0) / len(nps) * 10)
        print(
            f"fit_many workers={workers}: wall per 10 objects median {np.median(walls) * 1e3:.0f} ms, process CPU "
            f"{np.median(cpus) * 1e3:.0f} ms (load {_load()})"
        )


def _load() -> str:
    return " / ".join(f"{v:.2f}" for v in os.getloadavg())


def lmo() -> None:
    import cv2

    from normpos_grasp.camera.model import Camera
    from normpos_grasp.camera.render import render, visible_mask
    from normpos_grasp.templates.fit import estimate_normals
    from normpos_grasp.templates.library import load_library
    from normpos_grasp.templates.synthetic import make_normpos

    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo_sample"
    if not root.exists():
        print("LM-O sample not found; skipped")
        return
    lib = load_library(root / "models")
    t = lib.by_obj_id(5)
    cams = json.loads((root / "test/000002/scene_camera.json").read_text())["3"]
    k = np.array(cams["cam_K"]).reshape(3, 3)
    raw = cv2.imread(str(root / "test/000002/depth/000003.png"), cv2.IMREAD_UNCHANGED)
    if raw is None:
        print("LM-O depth image unreadable; skipped")
        return
    depth = raw.astype(float) * cams["depth_scale"] / 1000.0
    cam = Camera(k, depth.shape[1], depth.shape[0])
    gt_e = [g for g in json.loads((root / "test/000002/scene_gt.json").read_text())["3"] if g["obj_id"] == 5][0]
    u_, _, vt = np.linalg.svd(np.array(gt_e["cam_R_m2c"]).reshape(3, 3))
    gt = np.eye(4)
    gt[:3, :3] = u_ @ vt
    gt[:3, 3] = np.array(gt_e["cam_t_m2c"]) / 1000.0
    rend = render(cam, [(t.mesh, gt)])
    mask = visible_mask(rend.depth_m, depth, 0.015) & (rend.depth_m > 0) & (depth > 0)
    v, u = np.nonzero(mask)
    pix = np.column_stack([u, v])
    pts = cam.backproject(pix, depth[v, u])
    npos = make_normpos(pts, estimate_normals(pts, np.zeros(3)), pix, mask, t.label, 1)
    cases = [("GT-rendered visible mask", npos)]
    try:  # this project's model-free segmenter: the instance overlapping the can most
        from normpos_grasp.camera.model import RGBDFrame
        from normpos_grasp.measure.measure import measure_instances
        from normpos_grasp.perception.depth_segmenter import DepthSegmenter

        bgr = cv2.imread(str(root / "test/000002/rgb/000003.png"))
        if bgr is None:
            raise ImportError("LM-O rgb image unreadable")
        rgb = np.ascontiguousarray(bgr[:, :, ::-1]).astype(np.uint8)
        frame = RGBDFrame(rgb, depth, cam, 0.0)
        insts = DepthSegmenter().segment(frame)
        best = max(insts, key=lambda i: (i.mask & mask).sum() / (i.mask | mask).sum())
        iou = (best.mask & mask).sum() / (best.mask | mask).sum()
        cases.append((f"DepthSegmenter instance (IoU {iou:.2f} with the GT mask)", measure_instances(frame, [best])[0]))
    except ImportError as exc:
        print(f"depth segmenter unavailable: {exc}")
    for (src, npos_case), (name, o) in [
        (c, b) for c in cases for b in (("no bias", FitOptions()), ("bias 7.4 mm", FitOptions(depth_bias_m=0.0074)))
    ]:
        fit = fit_template(npos_case, t, o, FitContext(cam, depth))
        te = np.linalg.norm(fit.frame_from_object[:3, 3] - gt[:3, 3]) * 1000
        re = np.degrees(rotation_angle(gt[:3, :3].T @ fit.frame_from_object[:3, :3]))
        print(
            f"LM-O obj 5, {src}, {name}: {te:.2f} mm / {re:.2f} deg, "
            f"accepted={fit.accepted} score={fit.score:.3f} {fit.time_s * 1000:.0f} ms {fit.reason}"
        )


if __name__ == "__main__":
    main()
