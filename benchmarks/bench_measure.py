"""Norm-position measurement benchmark: centroid accuracy (noise-free and D435-like depth), speed, LM-O.

Scenes: 10 primitives (boxes, cylinders, spheres, 4-15 cm) on a table, a 640x480 D435-like camera
(f = 615 px) 0.6-1.0 m away, ray-cast with normpos_grasp.camera.render. Ground truth per object: the
centroid of the exact surface points hit by the rays through its visible mask pixels (the visible surface
as the camera samples it). Measurement: normpos_grasp.measure.measure_instances with default options
(edge-aware window estimate, S = 2) on the GT visible masks.

D435-like depth (../shared/reference/sensor_noise.md): RMS(z) = 3.6 mm * (z / 1 m)^2, half white and half
spatially correlated (Gaussian, sigma 2 px), 1 mm quantisation, dropouts (50 %) and flying pixels (25 %)
within 1 px of depth edges, a 16 px invalid band at the left edge, 1 % random holes.

    .venv/bin/python benchmarks/bench_measure.py [--scenes 20] [--seed 0] [--repeats 30]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from normpos_grasp.camera import Camera, RGBDFrame
from normpos_grasp.camera.render import Rendering, render, visible_mask
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.geometry.transforms import look_at
from normpos_grasp.measure.depth import DepthFillOptions, fill_depth
from normpos_grasp.measure.measure import MeasureOptions, backproject_depth, measure_instances
from normpos_grasp.records.instance import Instance

K = np.array([[615.0, 0.0, 319.5], [0.0, 615.0, 239.5], [0.0, 0.0, 1.0]])
LMO = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo_sample"


def make_scene(rng: np.random.Generator, n_objects: int = 10) -> tuple[Camera, list, Rendering]:
    import trimesh

    dist = rng.uniform(0.6, 1.0)
    tilt = rng.uniform(0.0, 0.5)
    eye = np.array([0.0, -np.sin(tilt) * dist, np.cos(tilt) * dist])
    camera = Camera(K, 640, 480, world_from_camera=look_at(eye, [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0)))
    table = trimesh.creation.box(extents=[2.0, 2.0, 0.02])
    meshes = [(table, make_pose(translation=[0.0, 0.0, -0.01]))]
    placed: list[np.ndarray] = []
    while len(meshes) < n_objects + 1:
        kind = rng.integers(3)
        size = rng.uniform(0.04, 0.15)
        if kind == 0:
            ext = np.array([size, rng.uniform(0.04, 0.15), rng.uniform(0.02, 0.1)])
            mesh, half_h, radius = trimesh.creation.box(extents=ext), ext[2] / 2, np.linalg.norm(ext[:2]) / 2
        elif kind == 1:
            h = rng.uniform(0.03, 0.12)
            mesh, half_h, radius = trimesh.creation.cylinder(radius=size / 2, height=h, sections=48), h / 2, size / 2
        else:
            mesh, half_h, radius = trimesh.creation.icosphere(subdivisions=3, radius=size / 2), size / 2, size / 2
        xy = rng.uniform(-0.22, 0.22, 2)
        if any(np.linalg.norm(xy - p[:2]) < radius + p[2] + 0.01 for p in placed):
            continue
        placed.append(np.array([xy[0], xy[1], radius]))
        rot = rotation_from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
        world_from_obj = make_pose(rot, [xy[0], xy[1], half_h])
        meshes.append((mesh, world_from_obj))
    cfw = camera.camera_from_world
    posed = [(m, cfw @ p) for m, p in meshes]
    return camera, posed, render(camera, posed)


def d435_depth(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    import cv2

    z = depth.copy()
    valid = z > 0
    sigma = 0.0036 * z**2
    white = rng.normal(size=z.shape)
    corr = cv2.GaussianBlur(rng.normal(size=z.shape), (0, 0), 2.0)
    corr /= corr.std()
    noisy = z + sigma * (np.sqrt(0.5) * white + np.sqrt(0.5) * corr)
    # depth edges: |dz| > 2 cm to a 4-neighbour, dilated by 1 px
    edge = np.zeros_like(valid)
    dzx = np.abs(np.diff(z, axis=1)) > 0.02
    dzy = np.abs(np.diff(z, axis=0)) > 0.02
    edge[:, 1:] |= dzx
    edge[:, :-1] |= dzx
    edge[1:] |= dzy
    edge[:-1] |= dzy
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    r = rng.random(z.shape)
    noisy[edge & (r < 0.5)] = 0.0
    fly = edge & (r >= 0.5) & (r < 0.75)
    far = cv2.dilate(z.astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.float64)
    near = -cv2.dilate(-np.where(valid, z, 99.0).astype(np.float32), np.ones((5, 5), np.uint8)).astype(np.float64)
    noisy[fly] = (near + rng.random(z.shape) * (far - near))[fly]
    noisy[:, :16] = 0.0
    noisy[rng.random(z.shape) < 0.01] = 0.0
    noisy[~valid] = 0.0
    return np.round(noisy * 1000.0) / 1000.0  # 1 mm steps


def gt_centroids(camera: Camera, rend: Rendering, n: int) -> tuple[list[Instance], list[np.ndarray]]:
    pts = backproject_depth(camera, rend.depth_m)
    wfc = camera.require_world_from_camera()
    instances, cents = [], []
    for k in range(1, n + 1):
        mask = rend.mask(k)
        if mask.sum() < 50:
            continue
        cam_pts = pts[mask]
        cents.append(cam_pts.mean(axis=0) @ wfc[:3, :3].T + wfc[:3, 3])
        instances.append(Instance(mask, f"obj{k}", 1.0, instance_id=len(instances) + 1))
    return instances, cents


def centroid_errors(scenes: int, seed: int, noise: bool, quant_m: float, options: MeasureOptions) -> np.ndarray:
    rng = np.random.default_rng(seed)
    errs = []
    for _ in range(scenes):
        camera, posed, rend = make_scene(rng)
        instances, cents = gt_centroids(camera, rend, len(posed) - 1)
        depth = d435_depth(rend.depth_m, rng) if noise else np.round(rend.depth_m / quant_m) * quant_m
        frame = RGBDFrame(np.zeros((480, 640, 3), np.uint8), depth, camera)
        items = measure_instances(frame, instances, options)
        for item, inst in zip(items, instances, strict=True):
            assert item.instance_id == inst.instance_id
            errs.append(np.linalg.norm(item.centroid - cents[inst.instance_id - 1]))
    return np.array(errs) * 1000.0


def _times(fn: Callable[[], object], repeats: int) -> tuple[float, float, float]:
    """Median wall-clock, minimum wall-clock and median CPU (process) time of `fn` in ms, after one warm-up
    call. On a shared, loaded machine the minimum is the best estimate of the unloaded cost."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.median(wall) * 1000), float(np.min(wall) * 1000), float(np.median(cpu) * 1000)


def timing(repeats: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    camera, posed, rend = make_scene(rng)
    instances, _ = gt_centroids(camera, rend, len(posed) - 1)
    depth = d435_depth(rend.depth_m, rng)
    frame = RGBDFrame(np.zeros((480, 640, 3), np.uint8), depth, camera)
    for name, opts in (("plain (paper)", DepthFillOptions(half_window=2)),
                       ("edge-aware", DepthFillOptions(half_window=2, edge_aware=True))):  # fmt: skip
        ts, tmin, cpu = _times(lambda o=opts: fill_depth(depth, o), repeats)
        print(f"  depth fill S=2, 640x480, {name:14s}: median {ts:6.2f} ms, min {tmin:6.2f} ms wall; "
              f"median {cpu:6.2f} ms CPU")  # fmt: skip
    for name, mopts in (("edge-aware fill", MeasureOptions()),
                        ("plain fill", MeasureOptions(depth=DepthFillOptions(half_window=2)))):  # fmt: skip
        ts, tmin, cpu = _times(lambda m=mopts: measure_instances(frame, instances, m), repeats)
        px = sum(i.pixel_count for i in instances)
        # load-robust estimate: each object timed alone, minimum over repeats, summed
        parts = sum(_times(lambda i=inst, m=mopts: measure_instances(frame, [i], m), repeats)[1] for inst in instances)
        print(f"  measure {len(instances)} objects ({px} mask px), {name:15s}: median {ts:6.2f} ms, min {tmin:6.2f} "
              f"ms wall; median {cpu:6.2f} ms CPU; sum of per-object minima {parts:6.2f} ms")  # fmt: skip


def lmo() -> None:
    import trimesh

    from normpos_grasp.io.bop import BopScene, load_mesh, read_models

    if not LMO.is_dir():
        print(f"  LM-O sample not found at {LMO}: skipped")
        return
    scene = BopScene(LMO / "test" / "000002")
    frame = scene.load_frame(3)
    mesh = load_mesh(read_models(LMO / "models")[5])
    gt = next(g for g in scene.gt(3) if g.obj_id == 5)
    rend = render(frame.camera, [(mesh, gt.camera_from_object)])
    mask = visible_mask(rend.depth_m, frame.depth_m, 0.015)
    posed = mesh.copy()
    posed.apply_transform(gt.camera_from_object)
    for name, opts in (("edge-aware S=2", MeasureOptions()),
                       ("plain S=2 (paper)", MeasureOptions(depth=DepthFillOptions(half_window=2))),
                       ("raw depth (S=0)", MeasureOptions(depth=DepthFillOptions(half_window=0)))):  # fmt: skip
        (item,) = measure_instances(frame, [Instance(mask, "obj_000005", 1.0)], opts)
        _, dist, _ = trimesh.proximity.closest_point(posed, item.points)
        within = np.mean(dist < 0.015) * 100
        med, p90 = np.median(dist) * 1000, np.percentile(dist, 90) * 1000
        print(f"  {name:18s}: {item.n_points} points, {within:5.1f} % within 15 mm of the posed model, "
              f"median {med:.2f} mm, p90 {p90:.2f} mm")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--timing-only", action="store_true", help="only the speed figures")
    args = parser.parse_args()
    if args.timing_only:
        print(f"Speed ({args.repeats} repeats)")
        timing(args.repeats, args.seed)
        return
    opts = MeasureOptions()
    print("Visible-surface centroid error, 10 objects per scene, camera 0.6-1.0 m")
    for label, noise, q in (("noise-free, float depth", False, 1e-9), ("noise-free, 0.1 mm steps", False, 1e-4),
                            ("noise-free, 1 mm steps", False, 1e-3)):  # fmt: skip
        e = centroid_errors(args.scenes, args.seed, noise, q, opts)
        print(f"  {label:26s}: median {np.median(e):.3f} mm, p95 {np.percentile(e, 95):.3f} mm, "
              f"max {e.max():.3f} mm over {e.size} objects")  # fmt: skip
    for label, mo in (("D435-like, edge-aware S=2", opts),
                      ("D435-like, plain S=2", MeasureOptions(depth=DepthFillOptions(half_window=2))),
                      ("D435-like, raw S=0", MeasureOptions(depth=DepthFillOptions(half_window=0)))):  # fmt: skip
        e = centroid_errors(args.scenes, args.seed, True, 1e-3, mo)
        print(f"  {label:26s}: median {np.median(e):.3f} mm, p95 {np.percentile(e, 95):.3f} mm, "
              f"max {e.max():.3f} mm over {e.size} objects")  # fmt: skip
    print(f"Speed ({args.repeats} repeats)")
    timing(args.repeats, args.seed)
    print("LM-O sample, object 5 (can), mask rendered from the model at the GT pose (BOP visibility, 15 mm)")
    lmo()


if __name__ == "__main__":
    main()
