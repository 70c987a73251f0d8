"""Benchmark of offline grasp simulation: physics validations per minute, and whole-pipeline picks per minute.

    .venv/bin/python benchmarks/bench_simulate.py [--repeats 5] [--episodes 0] [--count 8] [--seed 0] [--skip-physics]
        [--segmenter gt] [--cell examples/cells/...yaml]

Physics: every default part lies on a table with four neighbours around it and is picked top-down, centred,
across its narrowest horizontal side (2F-85) and, where its top is flat, with the suction cup; the median wall
time of `validate_grasp` per part (decomposition cached, as in a batch) gives validations per minute.
Episodes: with --episodes N, N bin-clearing scenes of the example cell run one after another in this process
(render, segment, measure, fit, plan, physics; as in one batch worker) and the figures are CPU seconds per scene,
attempted picks per CPU-minute and the projected time of a 100-scene run with one or two free cores.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from normpos_grasp.geometry.transforms import make_pose
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.physics import GripperSpec, collision_pieces, validate_grasp
from normpos_grasp.sim.physics_suction import check_seal

TABLE = [("table", make_pose(translation=[0.0, 0.0, -0.025]), np.array([1.0, 1.0, 0.05]))]


def _resting_pose(mesh) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Object frame as modelled, lifted so that its lowest point touches z = 0."""
    return make_pose(translation=[0.0, 0.0, -float(np.asarray(mesh.vertices)[:, 2].min())])


def _top_grasp(template, pose: np.ndarray, spec: GripperSpec) -> tuple[np.ndarray, float]:  # type: ignore[no-untyped-def]
    v = np.asarray(template.mesh.vertices) @ pose[:3, :3].T + pose[:3, 3]
    ext = v.max(axis=0) - v.min(axis=0)
    centre = (v.max(axis=0) + v.min(axis=0)) / 2.0
    closing = np.array([1.0, 0.0, 0.0]) if ext[0] <= ext[1] else np.array([0.0, 1.0, 0.0])
    width = float(ext[0] if ext[0] <= ext[1] else ext[1])
    top = float(v[:, 2].max())
    depth = min(spec.finger_length_m * 0.5, max(top - 0.003 - spec.tip_beyond_tcp_m, 0.0))
    z = np.array([0.0, 0.0, -1.0])
    rot = np.column_stack([closing, np.cross(z, closing), z])
    tcp = make_pose(rot, [centre[0], centre[1], max(top - depth, spec.tip_beyond_tcp_m + 0.002)])
    return tcp, min(width + 0.02, spec.stroke_m)


def bench_physics(repeats: int) -> None:
    parallel = GripperSpec.preset("2f85")
    suction = GripperSpec.preset("suction")
    library = default_part_library()
    print(f"{'part':10s} {'pieces':>6s} {'2f85':>8s} {'ms med':>8s} {'suction':>9s} {'ms med':>8s}")
    times: list[float] = []
    cpu: list[float] = []
    outcomes: dict[str, int] = {}
    for t in library:
        pose = _resting_pose(t.mesh)
        t0 = time.perf_counter()
        n_pieces = len(collision_pieces(t))
        decomp_ms = (time.perf_counter() - t0) * 1e3
        neighbours = [
            (
                library[(i + 1) % len(library)],
                _resting_pose(library[(i + 1) % len(library)].mesh) @ make_pose(translation=[dx, dy, 0.0]),
            )
            for i, (dx, dy) in enumerate([(0.12, 0.0), (-0.12, 0.0), (0.0, 0.12), (0.0, -0.12)])
        ]
        tcp, opening = _top_grasp(t, pose, parallel)
        runs = []
        res = None
        for _ in range(repeats):
            c0 = time.process_time()
            res = validate_grasp(t, pose, neighbours, TABLE, parallel, tcp, opening)
            runs.append(res.wall_time_s)
            cpu.append(time.process_time() - c0)
        assert res is not None
        outcomes[res.outcome] = outcomes.get(res.outcome, 0) + 1
        times.extend(runs)
        top = float((np.asarray(t.mesh.vertices) @ pose[:3, :3].T + pose[:3, 3])[:, 2].max())
        cup_tcp = make_pose(np.diag([1.0, -1.0, -1.0]), [tcp[0, 3], tcp[1, 3], top])
        mesh_world = t.mesh.copy()
        mesh_world.apply_transform(pose)
        s_out, s_ms = "-", float("nan")
        if check_seal(mesh_world, cup_tcp, suction.cup_diameter_m).sealed or t.name == "ring":
            s_runs = []
            for _ in range(repeats):
                c0 = time.process_time()
                sres = validate_grasp(t, pose, neighbours, TABLE, suction, cup_tcp, 0.0)
                s_runs.append(sres.wall_time_s)
                cpu.append(time.process_time() - c0)
            times.extend(s_runs)
            s_out, s_ms = sres.outcome, statistics.median(s_runs) * 1e3
            outcomes[s_out] = outcomes.get(s_out, 0) + 1
        print(
            f"{t.name:10s} {n_pieces:6d} {res.outcome:>8s} {statistics.median(runs) * 1e3:8.1f} {s_out:>9s} "
            f"{s_ms:8.1f}   (decomposition {decomp_ms:.0f} ms, once per process)"
        )
    med = statistics.median(times)
    cmed = statistics.median(cpu)
    print(
        f"physics validations: {len(times)}, median wall {med * 1e3:.1f} ms -> {60.0 / med:.0f} validations/min; "
        f"median CPU {cmed * 1e3:.1f} ms -> {60.0 / cmed:.0f} validations/min per free core; outcomes {outcomes}"
    )


def bench_episodes(cell: str, n: int, count: int, seed: int, segmenter: str) -> None:
    """Scenes run in this process (one after the other, as in one batch worker): CPU time per scene and per
    stage, so that the figure holds on a shared machine; the first scene also pays the per-process setup."""
    from normpos_grasp.simulate.episode import SimulationConfig, run_scene

    config = SimulationConfig(cell_path=cell, parts_per_scene=count, seed=seed, segmenter=segmenter)
    cpu, wall, picks, held = [], [], 0, 0
    pipeline_ms: list[float] = []
    physics_ms: list[float] = []
    for i in range(n):
        c0, t0 = time.process_time(), time.perf_counter()
        scene = run_scene(config, i)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
        picks += len(scene.picks)
        held += sum(p.success for p in scene.picks)
        pipeline_ms += [p.pipeline_ms for p in scene.picks]
        physics_ms += [p.physics_ms for p in scene.picks if p.physics]
        print(f"  scene {i}: {len(scene.picks)} picks, CPU {cpu[-1]:.1f} s, wall {wall[-1]:.1f} s")
    steady = cpu[1:] if n > 1 else cpu
    per_scene = statistics.median(steady)
    picks_per_scene = picks / n
    print(
        f"episodes: {n} scenes x {count} parts ({segmenter}), {picks} picks ({held} held); CPU {sum(cpu):.1f} s "
        f"(first scene {cpu[0]:.1f} s with the per-process setup), median {per_scene:.1f} s per later scene -> "
        f"{60.0 * picks_per_scene / per_scene:.1f} picks per CPU-minute; median wall per pick: pipeline "
        f"{statistics.median(pipeline_ms):.0f} ms, physics {statistics.median(physics_ms):.0f} ms"
    )
    for workers in (1, 2):
        est = (cpu[0] + per_scene * (100 / workers - 1)) / 60.0
        print(f"projected 100 scenes with --workers {workers} and {workers} free core(s): {est:.1f} min")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--episodes", type=int, default=0, help="bin-clearing scenes through the whole pipeline")
    parser.add_argument("--count", type=int, default=8, help="parts per episode scene")
    parser.add_argument("--seed", type=int, default=0, help="batch seed of the episode scenes")
    parser.add_argument("--segmenter", default="gt", choices=("gt", "depth"))
    parser.add_argument("--skip-physics", action="store_true", help="episodes only")
    parser.add_argument(
        "--cell", default=str(Path(__file__).resolve().parents[1] / "examples/cells/ur5e_bin_parallel.yaml")
    )
    args = parser.parse_args()
    if not args.skip_physics:
        bench_physics(args.repeats)
    if args.episodes > 0:
        bench_episodes(args.cell, args.episodes, args.count, args.seed, args.segmenter)


if __name__ == "__main__":
    main()
