"""Kinematics figures: FK agreement (pinocchio MJCF / MuJoCo / Robot vs the DH table), analytic IK speed and
success with round-trip error on random reachable poses, and mink differential-IK success and time.

Run: `nice -n 10 .venv/bin/python benchmarks/bench_kinematics.py [--poses 10000] [--mink-poses 100]`
(`--only one-pose` for the one-pose IK section alone). Timings are process CPU time (time.process_time: robust on
a shared machine), medians over repeats, one thread; the one-pose section times each call (perf_counter_ns).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import mujoco
import numpy as np
import pinocchio as pin

from normpos_grasp.kinematics import ROBOT_NAMES, IKOptions, Robot, dh_forward_kinematics
from normpos_grasp.kinematics.analytic_ik import ik_single
from normpos_grasp.kinematics.diff_ik import DiffIK, DiffIKNotConverged, DiffIKOptions


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return float(np.median(times))


def _random_q(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    lower, upper = robot.joint_limits
    return rng.uniform(np.maximum(lower, -2 * math.pi), np.minimum(upper, 2 * math.pi), size=(n, 6))


def _rot_err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    rel = np.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    skew = np.stack(
        [rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]], -1
    )
    return np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (np.trace(rel, axis1=-2, axis2=-1) - 1.0))


def fk_agreement(n: int) -> None:
    print(f"\n## FK agreement with the DH table ({n} random configurations per robot, max abs error)")
    print(
        "| robot | pinocchio MJCF pos m | MuJoCo pos m | Robot.fk pos m | max rot err rad | fk us | fk_batch us/pose |"
    )
    print("|---|---|---|---|---|---|---|")
    for name in ROBOT_NAMES:
        _fk_row(name, n)


def _fk_row(name: str, n: int) -> None:
    robot = Robot.load(name)
    rng = np.random.default_rng(0)
    qs = _random_q(robot, n, rng)
    ref = dh_forward_kinematics(robot.params, qs)
    pm = pin.buildModelFromMJCF(str(robot.mjcf_path))
    pd = pm.createData()
    fid = pm.getFrameId("flange")
    mj = robot.mujoco_model()
    md = mujoco.MjData(mj)
    e_pin = e_mj = e_rob = e_rot = 0.0
    for q, t in zip(qs, ref, strict=True):
        pin.framesForwardKinematics(pm, pd, q)
        p_pin = pd.oMf[fid].homogeneous
        md.qpos[:] = q
        mujoco.mj_kinematics(mj, md)
        p_mj = np.eye(4)
        p_mj[:3, :3] = md.site("flange").xmat.reshape(3, 3)
        p_mj[:3, 3] = md.site("flange").xpos
        p_rob = robot.fk(q)
        e_pin = max(e_pin, float(np.abs(p_pin[:3, 3] - t[:3, 3]).max()))
        e_mj = max(e_mj, float(np.abs(p_mj[:3, 3] - t[:3, 3]).max()))
        e_rob = max(e_rob, float(np.abs(p_rob[:3, 3] - t[:3, 3]).max()))
        e_rot = max(e_rot, float(_rot_err(np.stack([p_pin, p_mj, p_rob]), t[None]).max()))
    t_fk = _median_time(lambda: [robot.fk(q) for q in qs[:200]], 5) / 200
    t_batch = _median_time(lambda: robot.fk_batch(qs[:1000]), 5) / 1000
    print(f"| {name} | {e_pin:.1e} | {e_mj:.1e} | {e_rob:.1e} | {e_rot:.1e} | {t_fk * 1e6:.1f} | {t_batch * 1e6:.2f} |")


def analytic_ik(n: int) -> None:
    print(f"\n## Analytic IK ({n} random reachable poses per robot: FK of uniform random q in the limits)")
    print("success: some returned solution reproduces the pose within 1e-9 m and 1e-9 rad")
    print(
        "| robot | batch success | batch max pos err m | max rot err rad | batch us/pose (1000) | "
        "single raw us | robot.ik nearest-8 us | robot.ik all branches us (mean k) | robot.ik success |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name in ROBOT_NAMES:
        _ik_row(name, n)


def _ik_row(name: str, n: int) -> None:
    robot = Robot.load(name)
    rng = np.random.default_rng(1)
    qs = _random_q(robot, n, rng)
    poses = robot.fk_batch(qs)
    q8, valid = robot.ik_batch(poses)
    sol_poses = robot.fk_batch(np.nan_to_num(q8.reshape(-1, 6))).reshape(n, 8, 4, 4)
    pos_err = np.linalg.norm(sol_poses[..., :3, 3] - poses[:, None, :3, 3], axis=-1)
    rot_err = _rot_err(sol_poses, poses[:, None])
    ok = valid & (pos_err <= 1e-9) & (rot_err <= 1e-9)
    success = ok.any(axis=1).mean()
    best = np.where(valid, np.maximum(pos_err / 1e-9, rot_err / 1e-9), np.inf).argmin(axis=1)
    idx = np.arange(n)
    max_pos, max_rot = pos_err[idx, best].max(), rot_err[idx, best].max()
    t_batch = _median_time(lambda: robot.ik_batch(poses[:1000]), 7) / 1000
    lists = [p.tolist() for p in poses[:2000]]
    lengths = robot._lengths
    t_single = _median_time(lambda: [ik_single(lengths, p) for p in lists], 5) / len(lists)
    m = 300
    near_opts = IKOptions(all_branches=False)
    t_near = _median_time(lambda: [robot.ik(poses[i], qs[i], near_opts) for i in range(m)], 3) / m
    t_all = _median_time(lambda: [robot.ik(poses[i], qs[i]) for i in range(m)], 3) / m
    k_mean = np.mean([robot.ik(poses[i], qs[i]).shape[0] for i in range(m)])
    # robot.ik (single-pose path with limits/branches) round trip on 1,000 of the poses
    good = 0
    for i in range(1000):
        sols = robot.ik(poses[i], qs[i], near_opts)
        if sols.shape[0] == 0:
            continue
        sp = robot.fk_batch(sols)
        if (
            np.linalg.norm(sp[:, :3, 3] - poses[i, :3, 3], axis=1).min() <= 1e-9
            and _rot_err(sp, poses[i][None]).min() <= 1e-9
        ):
            good += 1
    print(
        f"| {name} | {success * 100:.2f} % | {max_pos:.1e} | {max_rot:.1e} | {t_batch * 1e6:.2f} | "
        f"{t_single * 1e6:.1f} | {t_near * 1e6:.0f} | {t_all * 1e6:.0f} ({k_mean:.0f}) | {good / 10:.1f} % |"
    )


def one_pose_ik(n: int, repeats: int) -> None:
    """Per-call time of the one-pose IK variants on the UR5e: median and p95 over n poses x repeats."""
    robot = Robot.load("ur5e")
    rng = np.random.default_rng(4)
    qs = _random_q(robot, n, rng)
    poses = robot.fk_batch(qs)
    lists = [p.tolist() for p in poses]
    near_opts, all_opts = IKOptions(all_branches=False), IKOptions()
    lengths = robot._lengths
    variants: dict[str, Callable[[int], object]] = {
        "closed form, plain Python (ik_single: 8 principal solutions, no limits)": lambda i: ik_single(
            lengths, lists[i]
        ),
        "robot.ik, nearest copy per solution, sorted": lambda i: robot.ik(poses[i], qs[i], near_opts),
        "robot.ik, every +-2 pi copy in the limits (256), sorted": lambda i: robot.ik(poses[i], qs[i], all_opts),
        "robot.ik_or_raise": lambda i: robot.ik_or_raise(poses[i], qs[i]),
        "Python path (robot._ik_python), nearest copy": lambda i: robot._ik_python(poses[i], qs[i], near_opts),
        "Python path (robot._ik_python), every copy": lambda i: robot._ik_python(poses[i], qs[i], all_opts),
    }
    for fn in variants.values():
        fn(0)  # loads the compiled kernel from numba's cache (or compiles it once)
    print(f"\n## One-pose IK (ur5e, {n} random reachable poses x {repeats} repeats, per call)")
    print(f"load average {' / '.join(f'{v:.2f}' for v in os.getloadavg())} (1 / 5 / 15 min)")
    print("| variant | median us | p95 us |")
    print("|---|---|---|")
    for label, fn in variants.items():
        times = []
        for _ in range(repeats):
            for i in range(n):
                t0 = time.perf_counter_ns()
                fn(i)
                times.append(time.perf_counter_ns() - t0)
        arr = np.array(times, dtype=np.float64) / 1e3
        print(f"| {label} | {np.median(arr):.1f} | {np.percentile(arr, 95):.1f} |")


def mink_ik(n: int) -> None:
    print(f"\n## mink differential IK (ur5e, {n} random reachable targets, to 0.1 mm / 0.1 deg, <= 300 iterations)")
    print("| start | ConfigurationLimit | success | median ms | median iterations | us/iteration |")
    print("|---|---|---|---|---|---|")
    robot = Robot.load("ur5e")
    rng = np.random.default_rng(2)
    qs = _random_q(robot, n, rng)
    noise = rng.normal(0.0, 0.3, size=qs.shape)
    home = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])
    for start_name in ("target + N(0, 0.3 rad)", "home"):
        for cfg_limit in (True, False):
            opts = DiffIKOptions(use_configuration_limit=cfg_limit, use_velocity_limit=False, max_iterations=300)
            solver = DiffIK(robot, opts)
            times, iters = [], []
            for i in range(n):
                start = np.clip(qs[i] + noise[i] if start_name != "home" else home, *robot.joint_limits)
                t0 = time.process_time()
                try:
                    res = solver.solve(start, robot.fk(qs[i]))
                except DiffIKNotConverged:
                    continue
                times.append(time.process_time() - t0)
                iters.append(res.iterations)
            per_it = sum(times) / max(sum(iters), 1)
            print(
                f"| {start_name} | {'on' if cfg_limit else 'off'} | {len(times) / n * 100:.0f} % | "
                f"{np.median(times) * 1e3:.1f} | {np.median(iters):.0f} | {per_it * 1e6:.0f} |"
            )
    print(f"\n## Cartesian straight lines (ur5e, {n} random 10 cm moves from random poses, 5 mm steps)")
    solver = DiffIK(robot, DiffIKOptions())
    ok, times, devs = 0, [], []
    for i in range(n):
        q0 = qs[i]
        if robot.singularity_distance(q0).min_singular_value < 0.05:
            q0 = home
        start = robot.fk(q0)
        direction = rng.normal(size=3)
        goal = start.copy()
        goal[:3, 3] += 0.1 * direction / np.linalg.norm(direction)
        t0 = time.process_time()
        try:
            path = solver.cartesian_path(q0, goal, step_m=0.005)
        except DiffIKNotConverged:
            continue
        times.append(time.process_time() - t0)
        ok += 1
        rel = robot.fk_batch(path)[:, :3, 3] - start[:3, 3]
        u = (goal[:3, 3] - start[:3, 3]) / 0.1
        devs.append(np.linalg.norm(rel - np.outer(rel @ u, u), axis=1).max())
    print(
        f"success {ok / n * 100:.0f} % (failures: lines through singularities or limits), median "
        f"{np.median(times) * 1e3:.0f} ms per 10 cm path (21 waypoints), max deviation from the line "
        f"{max(devs) * 1e3:.3f} mm"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=10_000, help="random poses per robot for analytic IK")
    parser.add_argument("--fk-configs", type=int, default=1_000, help="random configurations per robot for FK")
    parser.add_argument("--mink-poses", type=int, default=100, help="targets for mink differential IK")
    parser.add_argument("--one-pose-poses", type=int, default=2_000, help="poses of the one-pose IK section")
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the one-pose IK section")
    parser.add_argument("--only", choices=("one-pose",), help="run one section only")
    args = parser.parse_args()
    print("# bench_kinematics")
    one_pose_ik(args.one_pose_poses, args.repeats)
    if args.only:
        return
    fk_agreement(args.fk_configs)
    analytic_ik(args.poses)
    mink_ik(args.mink_poses)


if __name__ == "__main__":
    main()
