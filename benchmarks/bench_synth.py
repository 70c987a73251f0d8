"""Synthetic-scene speed: per-frame render + sensor time at 640x480 with 10 parts, and a 100-frame BOP export.

Run: .venv/bin/python benchmarks/bench_synth.py [--frames-per-scene 10 --scenes 10 --repeats 20]
Prints medians (and p90) over repeats; says which renderer ran.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from normpos_grasp.sim.cameras import CameraOptions, sample_camera
from normpos_grasp.sim.dataset import write_bop_dataset
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.render import make_renderer
from normpos_grasp.sim.scene import SceneOptions, compose_scene
from normpos_grasp.sim.sensor import sensor_preset


def _stats(xs: list[float]) -> str:
    return f"median {1000 * statistics.median(xs):7.1f} ms   p90 {1000 * float(np.percentile(xs, 90)):7.1f} ms"


def bench_frames(backend: str, repeats: int, sensor_name: str) -> None:
    lib = default_part_library()
    t0 = time.perf_counter()
    layout = compose_scene(SceneOptions(count=10, seed=1), lib)
    t_physics = time.perf_counter() - t0
    cam_opts = CameraOptions(sensor=sensor_name, resolution=(640, 480))
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    renderer = make_renderer(layout, 640, 480, backend)
    t_build = time.perf_counter() - t0
    sensor = sensor_preset(sensor_name)
    warm_cam = sample_camera(cam_opts, layout.container_centre(), rng)
    sensor.apply(renderer.render(warm_cam), warm_cam, rng)  # warm-up (GL pipeline, noise pool)
    t_render, t_sensor, t_total, cpu_total = [], [], [], []
    for _ in range(repeats):
        cam = sample_camera(cam_opts, layout.container_centre(), rng)
        cpu0 = time.process_time()
        a = time.perf_counter()
        out = renderer.render(cam)
        b = time.perf_counter()
        sensor.apply(out, cam, rng)
        c = time.perf_counter()
        cpu_total.append(time.process_time() - cpu0)
        t_render.append(b - a)
        t_sensor.append(c - b)
        t_total.append(c - a)
    renderer.close()
    print(f"[{out.backend}] 640x480, 10 parts, sensor {sensor_name}, {repeats} views")
    print(f"  physics settle (one scene)      {1000 * t_physics:7.1f} ms   renderer build {1000 * t_build:6.1f} ms")
    print(f"  render RGB+depth+ids+masks      {_stats(t_render)}")
    print(f"  sensor noise (depth + RGB)      {_stats(t_sensor)}")
    print(f"  frame total (wall)              {_stats(t_total)}")
    print(f"  frame total (process CPU time)  {_stats(cpu_total)}   (all threads, incl. the software GL rasteriser)")


def bench_dataset(scenes: int, frames: int, sensor_name: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        cpu0 = time.process_time()
        write_bop_dataset(tmp + "/ds", scenes, frames, sensor=sensor_name, resolution=(640, 480), seed=0)
        dt = time.perf_counter() - t0
        cpu = time.process_time() - cpu0
    n = scenes * frames
    print(
        f"BOP export: {n} frames ({scenes} scenes x {frames} views, 10 parts, {sensor_name}, 640x480) in {dt:.1f} s "
        f"= {1000 * dt / n:.0f} ms/frame including physics, rendering, noise and PNG/JSON writing "
        f"(process CPU {cpu:.1f} s)"
    )
    print(f"load average after: {os.getloadavg()[0]:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--frames-per-scene", type=int, default=10)
    parser.add_argument("--sensor", default="d435")
    parser.add_argument("--skip-raycast", action="store_true")
    args = parser.parse_args()
    print(f"cpu cores: {os.cpu_count()}, load average: {os.getloadavg()[0]:.2f}, MUJOCO_GL={os.environ['MUJOCO_GL']}")
    bench_frames("auto", args.repeats, args.sensor)
    if not args.skip_raycast:
        bench_frames("raycast", max(3, args.repeats // 4), args.sensor)
    bench_dataset(args.scenes, args.frames_per_scene, args.sensor)


if __name__ == "__main__":
    main()
