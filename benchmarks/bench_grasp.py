"""Grasp selection and pick-and-place planning on synthetic bin scenes built from ground truth.

For each scene (10 parts of the default library dropped into a bin and settled with MuJoCo) the ground-truth
poses are handed to `plan_pick` as accepted fits. Printed: fits -> plan time (median / p90 over scenes, each the
median of `--repeats` runs) with the stage split, candidate counts, the rejection counts by reason, the share of
scenes with an uncovered reachable part where a plan was found, an independent collision check of every chosen
plan against the ground truth (trimesh manager + the kinematics stage's own FK and gripper shapes), and the
largest waypoint FK error.

    .venv/bin/python benchmarks/bench_grasp.py --scenes 40 --repeats 3

`--digest PATH` writes, per scene, the plan's status, rejection counts, the chosen candidate (target, grasp pose)
and the waypoints' joints (rounded to 1e-9) as JSON, to compare two versions of the planner on the same bins
(`--compare PATH` reads such a file and prints the scenes whose plan differs). `--profile N` runs the timed plans
under cProfile and prints the N functions with the most own time (timings under the profiler are not comparable).
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import json
import os
import pstats
import time
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.config import BinSpec, BoxSpec, CellConfig
from normpos_grasp.geometry import make_pose
from normpos_grasp.kinematics import Gripper, Robot
from normpos_grasp.planning import ArmModel, PlanOptions, plan_pick
from normpos_grasp.records.template import TemplateFit
from normpos_grasp.report.scene3d import capsule_mesh
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.scene import SceneOptions, compose_scene

ROOT = Path(__file__).resolve().parents[1]


def scene_cell(layout, gripper: str) -> CellConfig:  # type: ignore[no-untyped-def]
    """The example UR5e cell moved onto the simulated scene: bin at the origin, robot 0.5 m behind it."""
    base = load_cell(ROOT / "examples" / "cells" / "ur5e_bin_parallel.yaml")
    o = layout.options
    boxes = tuple(BoxSpec(n, p, s) for n, p, s in layout.static_boxes)
    bin_spec = BinSpec(
        make_pose(None, [0, 0, o.bin_floor_thickness_m]),
        np.array([*o.bin_inner_size_m, o.bin_wall_height_m]),
        o.bin_wall_thickness_m,
    )
    from normpos_grasp.collision import tool_from_gripper

    return replace(
        base,
        world_from_base=make_pose(np.diag([-1.0, -1.0, 1.0]), [-0.5, 0.0, 0.0]),
        static_boxes=boxes,
        bin=bin_spec,
        tool=tool_from_gripper(Gripper.load(gripper)),
        places=(replace(base.places[0], world_from_tcp=make_pose(np.diag([1.0, -1.0, -1.0]), [-0.35, -0.38, 0.0])),),
    )


def uncovered_reachable(layout, cell: CellConfig) -> list[int]:  # type: ignore[no-untyped-def]
    """Parts with no other part above their footprint whose top centre a top-down TCP can reach."""
    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    meshes = [layout.part_mesh_world(i) for i in range(layout.n_parts)]
    out = []
    for i, m in enumerate(meshes):
        lo, hi = m.bounds
        covered = False
        for j, other in enumerate(meshes):
            if j == i:
                continue
            v = other.vertices
            inside = np.all((v[:, :2] >= lo[:2] - 0.005) & (v[:, :2] <= hi[:2] + 0.005), axis=1)
            if np.any(inside & (v[:, 2] > hi[2] - 0.002)):
                covered = True
                break
        if covered:
            continue
        top = make_pose(np.diag([1.0, -1.0, -1.0]), [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
        _, ok = arm.ik(top @ np.linalg.inv(cell.tool.flange_from_tcp))
        if ok.any():
            out.append(i)
    return out


def independent_check(plan, cell: CellConfig, layout, gripper_name: str) -> list[str]:  # type: ignore[no-untyped-def]
    """Collisions of the chosen plan against the GT world, computed without the planner's collision code."""
    robot = Robot.load(cell.robot_model)
    gripper = Gripper.load(gripper_name)
    target = plan.chosen.candidate.target
    env = trimesh.collision.CollisionManager()
    for box in cell.static_boxes:
        env.add_object(box.name, trimesh.creation.box(box.size), box.world_from_box)
    for k in range(layout.n_parts):
        if k != target:
            env.add_object(f"part{k}", layout.templates[k].mesh, layout.world_from_object[k])
    arm = trimesh.collision.CollisionManager()
    shapes = [s for s in robot.collision_geometry if s.link != "base"]
    for i, s in enumerate(shapes):
        r, length = s.size
        geom = capsule_mesh(r, length) if s.kind == "capsule" else trimesh.creation.cylinder(r, length)
        arm.add_object(f"a{i}", geom)
    tool = trimesh.collision.CollisionManager()
    tshapes = gripper.collision_shapes(plan.chosen.candidate.opening_m if gripper.kind == "parallel" else None)
    for i, s in enumerate(tshapes):
        geom = trimesh.creation.box(s.size) if s.kind == "box" else trimesh.creation.cylinder(s.size[0], s.size[1])
        tool.add_object(f"t{i}", geom)
    held = trimesh.collision.CollisionManager()
    held.add_object("held", layout.templates[target].mesh)
    grasp_tcp = plan.chosen.candidate.world_from_tcp
    tcp_from_object = np.linalg.inv(grasp_tcp) @ layout.world_from_object[target]
    traj = plan.trajectory
    t_of: dict[str, float] = {}
    start = 0
    for w in plan.waypoints:  # in order: a waypoint is reached after the previous one (lift may equal pre_grasp)
        k = start + int(np.argmin(np.abs(traj.q[start:] - w.q).sum(axis=1)))
        t_of[w.name] = float(traj.t[k])
        start = k
    base = cell.world_from_base
    problems = []
    for t, q in zip(traj.t[::2], traj.q[::2], strict=True):
        links = robot.link_poses(q)
        for i, s in enumerate(shapes):
            arm.set_transform(f"a{i}", base @ links[s.link] @ s.link_from_shape)
        if env.in_collision_other(arm):
            problems.append(f"arm t={t:.2f}")
        world_from_tcp = base @ links["flange"] @ gripper.flange_from_tcp
        for i, s in enumerate(tshapes):
            tool.set_transform(f"t{i}", world_from_tcp @ s.link_from_shape)
        if env.in_collision_other(tool):
            problems.append(f"tool t={t:.2f}")
        if t_of["lift"] <= t <= t_of["pre_place"]:
            held.set_transform("held", world_from_tcp @ tcp_from_object)
            if env.in_collision_other(held):
                problems.append(f"held t={t:.2f}")
    return problems


def _sha(a: np.ndarray, decimals: int) -> str:
    return hashlib.sha1(np.round(a, decimals).tobytes()).hexdigest()[:16]


def plan_digest(plan) -> dict[str, object]:  # type: ignore[no-untyped-def]
    """Status, counts, chosen grasp and waypoint joints of one plan, rounded so that equal plans compare equal."""
    chosen = plan.chosen
    return {
        "status": plan.status,
        "counts": dict(sorted(plan.counts.items())),
        "target": None if chosen is None else int(chosen.candidate.target),
        "grasp": None if chosen is None else np.round(chosen.candidate.world_from_tcp, 9).tolist(),
        "waypoints": [[w.name, np.round(w.q, 9).tolist()] for w in plan.waypoints],
        "trajectory": None if plan.trajectory is None else _sha(plan.trajectory.q, 9) + _sha(plan.trajectory.t, 6),
        "verdicts": hashlib.sha1("|".join(f"{e.reason}:{e.pose}" for e in plan.evaluations).encode()).hexdigest(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--parts", type=int, default=10)
    ap.add_argument("--gripper", default="2f85")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--digest", type=Path, default=None, help="write each scene's plan as JSON here")
    ap.add_argument("--compare", type=Path, default=None, help="a --digest file to compare the plans with")
    ap.add_argument("--profile", type=int, default=0, help="profile the timed plans, print the top N functions")
    args = ap.parse_args()
    digests: list[dict[str, object]] = []
    prof = cProfile.Profile() if args.profile else None
    library = default_part_library()
    times: list[float] = []
    cpu_times: list[float] = []
    n_cands: list[int] = []
    stages: defaultdict[str, float] = defaultdict(float)
    reasons: Counter[str] = Counter()
    eligible = found = 0
    collisions = 0
    fk_err = 0.0
    statuses: Counter[str] = Counter()
    robot = Robot.load("ur5e")
    t_scenes = 0.0
    load_before = os.getloadavg()[0]
    for s in range(args.scenes):
        t0 = time.perf_counter()
        layout = compose_scene(SceneOptions(count=args.parts, seed=args.seed + s), library)
        t_scenes += time.perf_counter() - t0
        cell = scene_cell(layout, args.gripper)
        fits = [
            TemplateFit(t, layout.world_from_object[k], 1.0, 0.0, 1.0, 1.0, 0.0, True, instance_id=k + 1)
            for k, t in enumerate(layout.templates)
        ]
        runs, cpu_runs = [], []
        plan = plan_pick(fits, [], cell, PlanOptions())  # warm-up: template BVHs and synthesis are cached per part
        for _ in range(args.repeats):
            if prof is not None:
                prof.enable()
            t0, c0 = time.perf_counter(), time.process_time()
            plan = plan_pick(fits, [], cell, PlanOptions())
            if prof is not None:
                prof.disable()
            runs.append((time.perf_counter() - t0) * 1e3)
            cpu_runs.append((time.process_time() - c0) * 1e3)
            for k, v in plan.timing_ms.items():
                stages[k] += v
        times.append(float(np.median(runs)))
        cpu_times.append(float(np.median(cpu_runs)))
        n_cands.append(len(plan.evaluations))
        reasons.update(plan.counts)
        statuses[plan.status] += 1
        digests.append(plan_digest(plan))
        good = uncovered_reachable(layout, cell)
        if good:
            eligible += 1
            found += plan.status == "ok"
        if plan.status == "ok":
            probs = independent_check(plan, cell, layout, args.gripper)
            if probs:
                collisions += 1
                print(f"  scene {s}: independent check found {probs[:3]}")
            tool = Gripper.load(args.gripper)
            for w in plan.waypoints:
                fk = cell.world_from_base @ robot.fk(w.q) @ tool.flange_from_tcp
                fk_err = max(fk_err, float(np.abs(fk[:3, 3] - w.world_from_tcp[:3, 3]).max()))
    n = args.scenes
    t = np.array(times)
    print(
        f"bench_grasp: {n} GT bin scenes x {args.parts} parts, gripper {args.gripper}, UR5e, "
        f"{args.repeats} repeats each (scene generation {t_scenes:.1f} s, not timed below)"
    )
    c = np.array(cpu_times)
    print(f"fits -> plan wall: median {np.median(t):.1f} ms, p90 {np.percentile(t, 90):.1f} ms, max {t.max():.1f} ms")
    print(
        f"fits -> plan CPU time of this process: median {np.median(c):.1f} ms, p90 {np.percentile(c, 90):.1f} ms "
        f"(load average before / after: {load_before:.1f} / {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)"
    )
    print("  stage means, wall (ms): " + ", ".join(f"{k} {v / (n * args.repeats):.1f}" for k, v in stages.items()))
    print(f"candidates per scene: median {np.median(n_cands):.0f} (min {min(n_cands)}, max {max(n_cands)})")
    print(f"status: {dict(statuses)}")
    print(f"plan found when an uncovered part is in reach: {found}/{eligible} = {100 * found / max(eligible, 1):.1f} %")
    print(f"chosen plans colliding per the independent GT check: {collisions}/{statuses['ok']}")
    print(f"max waypoint FK error vs TCP pose: {fk_err * 1e3:.6f} mm")
    print("rejections by reason (all scenes): " + ", ".join(f"{k} {v}" for k, v in reasons.most_common()))
    if args.digest is not None:
        args.digest.write_text(json.dumps(digests, indent=1))
    if args.compare is not None:
        old = json.loads(args.compare.read_text())
        diff = [s for s, (a, b) in enumerate(zip(old, digests, strict=False)) if a != b]
        same = len(digests) - len(diff)
        print(f"plans compared with {args.compare}: {same}/{len(digests)} identical; differ: {diff}")
    if prof is not None:
        pstats.Stats(prof).sort_stats("tottime").print_stats(args.profile)


if __name__ == "__main__":
    main()
