"""Verification benchmark: can a wrong template or a wrong pose pass? One pose per object? Real depth bias.

Synthetic part (normpos_grasp.sim, the built-in 8-part library, D435 noise, camera 0.5-1.0 m, visible fraction
>= 0.3, ground-truth masks): every object fitted with its own template, with each of the 7 wrong templates forced
(`fit_template`), and with all templates competing (label '', `fit_best`); accepted shares, and precision against
score over every accepted fit (score bin -> share of accepted poses that are right: the right template and
ADD(-S) < 0.1 d).

LM-O part (/work/shared/data/lmo_sample, one real Kinect frame, the can with ground truth): the depth bias from the
table plane (`measure.depth_bias.estimate_depth_bias`; the table plane is derived from the can's ground-truth pose
here because the frame has no extrinsics; the README's check value is depth minus the GT-rendered can surface),
then the whole frame through `pipeline.perceive` with the GT-rendered mask and with the project's depth segmenter
(`DepthSegmenter`), without and with the estimated bias corrected: accepted poses, the top-1 pose's error, and
accepted poses on the can beyond the first.

    .venv/bin/python benchmarks/bench_verify.py [--frames 4] [--seed 1] [--no-lmo]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_fit import sym_errors

from normpos_grasp.geometry.transforms import rotation_angle
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_best, fit_template
from normpos_grasp.templates.prepared import prepare

BINS = (0.0, 0.5, 0.6, 0.7, 0.8, 0.9, 1.01)


def precision_table(scored: list[tuple[float, bool]], title: str) -> None:
    """Print score bin -> accepted count and share right."""
    print(f"precision against score ({title}):")
    s = np.array([x[0] for x in scored]) if scored else np.zeros(0)
    ok = np.array([x[1] for x in scored], dtype=bool) if scored else np.zeros(0, dtype=bool)
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        sel = (s >= lo) & (s < hi)
        if sel.any():
            print(f"  score [{lo:.2f}, {min(hi, 1.0):.2f}): {int(sel.sum()):4d} accepted, {ok[sel].mean():.3f} right")
        else:
            print(f"  score [{lo:.2f}, {min(hi, 1.0):.2f}):    0 accepted")


def synthetic(frames: int, seed: int) -> list[tuple[float, bool]]:
    from normpos_grasp.measure.measure import measure_instances
    from normpos_grasp.sim.cameras import CameraOptions
    from normpos_grasp.sim.dataset import generate_frame
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.sim.scene import SceneOptions

    library = default_part_library()
    opts = FitOptions()
    scored: list[tuple[float, bool]] = []
    n_obj = n_right = 0
    forced = forced_acc = 0
    comp = comp_right = comp_wrong = 0
    t0 = time.perf_counter()
    for f in range(frames):
        sf = generate_frame(
            SceneOptions(count=10, seed=seed * 1000 + f),
            "d435",
            CameraOptions(distance_m=(0.5, 1.0)),
            seed=seed * 7919 + f,
            library=library,
        )
        insts = [i for i in sf.instances if sf.visib_fractions[i.source_id] >= 0.3]
        nps = measure_instances(sf.frame, insts)
        ctx = FitContext(sf.frame.camera, sf.frame.depth_m)
        for n, inst in zip(nps, insts, strict=True):
            truth = sf.layout.templates[inst.source_id]
            gt = sf.world_from_object[inst.source_id]
            n_obj += 1
            for t in library:
                fit = fit_template(n, t, opts, ctx)
                right = t.name == truth.name
                ok = right and sym_errors(t, fit.frame_from_object, gt)[2] < 0.1 * prepare(t).diameter
                if right:
                    n_right += int(fit.accepted and ok)
                else:
                    forced += 1
                    forced_acc += int(fit.accepted)
                if fit.accepted:
                    scored.append((fit.score, ok))
            fb = fit_best(replace(n, label=""), library, opts, ctx)
            comp += 1
            if fb.accepted:
                ok = fb.template.name == truth.name
                comp_right += int(ok)
                comp_wrong += int(not ok)
    print(
        f"synthetic: {n_obj} objects in {frames} frames (visible fraction >= 0.3), {time.perf_counter() - t0:.0f} s\n"
        f"  right template: {n_right}/{n_obj} accepted and right\n"
        f"  wrong template forced: {forced_acc} of {forced} accepted ({100 * forced_acc / max(forced, 1):.2f} %)\n"
        f"  all {len(library)} templates competing (label ''): {comp_right}/{comp} right template accepted, "
        f"{comp_wrong} wrong template accepted"
    )
    return scored


def lmo(scored: list[tuple[float, bool]]) -> None:
    import cv2

    from normpos_grasp.camera.model import Camera, RGBDFrame
    from normpos_grasp.camera.render import render
    from normpos_grasp.measure.depth_bias import correct_depth, estimate_depth_bias
    from normpos_grasp.perception.depth_segmenter import DepthSegmenter
    from normpos_grasp.pipeline import PipelineOptions, perceive
    from normpos_grasp.records.instance import Instance
    from normpos_grasp.templates.library import load_library

    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo_sample"
    if not root.exists():
        print("LM-O sample not found; skipped")
        return
    t = load_library(root / "models").by_obj_id(5)
    cams = json.loads((root / "test/000002/scene_camera.json").read_text())["3"]
    raw = cv2.imread(str(root / "test/000002/depth/000003.png"), cv2.IMREAD_UNCHANGED)
    bgr = cv2.imread(str(root / "test/000002/rgb/000003.png"))
    if raw is None or bgr is None:
        print("LM-O images unreadable; skipped")
        return
    depth = raw.astype(float) * cams["depth_scale"] / 1000.0
    cam = Camera(np.array(cams["cam_K"]).reshape(3, 3), depth.shape[1], depth.shape[0])
    gt_e = [g for g in json.loads((root / "test/000002/scene_gt.json").read_text())["3"] if g["obj_id"] == 5][0]
    u_, _, vt = np.linalg.svd(np.array(gt_e["cam_R_m2c"]).reshape(3, 3))
    gt = np.eye(4)
    gt[:3, :3] = u_ @ vt
    gt[:3, 3] = np.array(gt_e["cam_t_m2c"]) / 1000.0
    rend = render(cam, [(t.mesh, gt)])
    near = (rend.depth_m > 0) & (depth > 0) & (np.abs(depth - rend.depth_m) < 0.015)
    print(
        f"LM-O: depth - GT-rendered can surface over {int(near.sum())} pixels: median "
        f"{np.median(depth[near] - rend.depth_m[near]) * 1000:+.2f} mm (the check value)"
    )
    # table plane: the can stands on it (model z up, base at the model's lowest z)
    zmin = float(np.asarray(t.mesh.vertices)[:, 2].min())
    up = gt[:3, 2]
    base = gt[:3, 3] + up * zmin
    plane = np.concatenate([up, [-float(up @ base)]])
    est = estimate_depth_bias(cam, depth, plane)
    print(
        f"LM-O: estimated depth bias from the table plane {est.bias_m * 1000:+.2f} mm (spread "
        f"{est.spread_m * 1000:.1f} mm, {est.n_plane} plane pixels, tilt {est.tilt_deg:.2f} deg, valid "
        f"{100 * est.valid_share:.0f} %){' ' + '; '.join(est.warnings) if est.warnings else ''}"
    )
    rgb = np.ascontiguousarray(bgr[:, :, ::-1]).astype(np.uint8)
    gt_mask = (rend.depth_m > 0) & (depth > 0) & (depth - rend.depth_m < 0.015)
    segmenter = DepthSegmenter()
    can_r = 0.5 * prepare(t).diameter
    for bias_name, bias in (("raw depth", 0.0), (f"bias {est.corrected * 1000:+.1f} mm corrected", est.corrected)):
        d = correct_depth(depth, bias)
        frame = RGBDFrame(rgb, d, cam, 0.0)
        for src in ("GT-rendered mask", "DepthSegmenter"):
            insts = [Instance(mask=gt_mask, label="", score=1.0, instance_id=1)] if src.startswith("GT") else None
            res = perceive(frame, segmenter if insts is None else None, [t], PipelineOptions(), instances=insts)
            acc = sorted(res.accepted_fits, key=lambda f: f.score, reverse=True)
            on_can = [f for f in acc if np.linalg.norm(f.frame_from_object[:3, 3] - gt[:3, 3]) < can_r]
            for f in acc:
                te_f = np.linalg.norm(f.frame_from_object[:3, 3] - gt[:3, 3])
                re_f = np.degrees(rotation_angle(gt[:3, :3].T @ f.frame_from_object[:3, :3]))
                scored.append((f.score, bool(te_f < 0.01 and re_f < 5.0)))
            head = f"LM-O {src}, {bias_name}: {len(res.instances)} instances, {len(acc)} accepted poses"
            if not acc:
                print(f"{head}; no pose")
                continue
            top = acc[0]
            te = np.linalg.norm(top.frame_from_object[:3, 3] - gt[:3, 3]) * 1000
            re = np.degrees(rotation_angle(gt[:3, :3].T @ top.frame_from_object[:3, :3]))
            dups = sum(1 for f in res.fits if "duplicate_of" in f.extra)
            print(
                f"{head}; top-1 {te:.2f} mm / {re:.2f} deg (score {top.score:.3f}, within 5 mm / 3 deg: "
                f"{te <= 5 and re <= 3}); accepted on the can: {len(on_can)} (second pose on it: {len(on_can) > 1}); "
                f"{dups} duplicates suppressed"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-lmo", action="store_true", help="skip the LM-O real frame")
    args = ap.parse_args()
    scored = synthetic(args.frames, args.seed) if args.frames > 0 else []
    if not args.no_lmo:
        lmo(scored)
    precision_table(scored, "every accepted fit above: synthetic right/forced and LM-O")


if __name__ == "__main__":
    main()
