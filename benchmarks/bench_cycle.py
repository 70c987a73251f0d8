"""Pick-and-place cycle time: the arm-motion duration of a plan (home -> bin -> grasp -> place), before/after.

Bins: `loop.SyntheticBinSource` in examples/cells/ur5e_bin_parallel.yaml (`--parts` physics-settled parts, seeds
`--seed`, `--seed` + 1, ...), perceived with the frame's true masks (`perceive`, everything after segmentation as
the pipeline runs it) and planned with `plan_pick` once per timing variant, same fits, same deterministic planner:
- trapezoid: `TimingOptions(method='trapezoid')`, rest-to-rest trapezoids per segment (the timing before Ruckig);
- ruckig: the default (`planning.timing.time_path`): time-optimal, jerk-limited, blending through waypoints;
- ruckig, no blends: the same profiles resting at every waypoint (what blending adds);
- ruckig, jerk x2: `--jerk-factor` times the default jerk cap (what the jerk cap costs).
Every plan is then checked as execution checks it before sending: plan.json round trip, `execution.plan.check_plan`
with `SafetyLimits.from_cell` (waypoints, segments, every trajectory sample: joint limits, workspace, speed and
acceleration caps by finite differences); the largest sample speed, acceleration and jerk are printed as shares of
the caps, and the largest distance of the TCP from its straight line between the Cartesian waypoints.

    nice -n 10 .venv/bin/python benchmarks/bench_cycle.py [--bins 6] [--parts 10] [--seed 5200]
"""

from __future__ import annotations

import argparse
import os
from dataclasses import replace
from typing import Any

import numpy as np

from normpos_grasp.cell import load_cell
from normpos_grasp.execution.plan import check_plan, parse_plan
from normpos_grasp.execution.safety import SafetyLimits
from normpos_grasp.kinematics.ur_params import dh_forward_kinematics, ur_params
from normpos_grasp.loop import SyntheticBinSource
from normpos_grasp.pipeline import PipelineOptions, perceive
from normpos_grasp.planning.plan import PlanOptions, plan_pick
from normpos_grasp.planning.timing import TimingOptions
from normpos_grasp.records.plan import PickPlan
from normpos_grasp.sim.parts import default_part_library

CELL = "examples/cells/ur5e_bin_parallel.yaml"
LINES = (("entry", "pre_grasp"), ("pre_grasp", "grasp"), ("grasp", "lift"), ("lift", "retreat"))
LINES += (("pre_place", "place"), ("place", "post_place"))


def line_deviation_mm(plan: PickPlan, cell: Any) -> float:
    """Largest distance (mm) of a trajectory sample's TCP from the straight line of its Cartesian segment."""
    traj = plan.trajectory
    assert traj is not None
    names = [w.name for w in plan.waypoints]
    wq = [w.q for w in plan.waypoints]
    idx = [int(np.argmin(np.abs(traj.q - q).max(axis=1))) for q in wq]
    for k in range(1, len(idx)):  # in order (post_place repeats pre_place)
        if idx[k] < idx[k - 1]:
            later = np.abs(traj.q[idx[k - 1] :] - wq[k]).max(axis=1)
            idx[k] = idx[k - 1] + int(np.argmin(later))
    world_tcp = cell.world_from_base @ dh_forward_kinematics(ur_params(cell.robot_model), traj.q)
    tcp = (world_tcp @ cell.tool.flange_from_tcp)[:, :3, 3]
    worst = 0.0
    for a, b in LINES:
        i, j = idx[names.index(a)], idx[names.index(b)]
        p0, p1 = (
            plan.waypoints[names.index(a)].world_from_tcp[:3, 3],
            plan.waypoints[names.index(b)].world_from_tcp[:3, 3],
        )
        u = (p1 - p0) / max(float(np.linalg.norm(p1 - p0)), 1e-12)
        rel = tcp[i : j + 1] - p0
        worst = max(worst, float(np.linalg.norm(rel - np.outer(rel @ u, u), axis=1).max()))
    return worst * 1e3


def cap_shares(plan: PickPlan, limits: SafetyLimits, jerk_cap: float) -> tuple[float, float, float]:
    """Largest |speed|, |acceleration| and |jerk| of the samples (finite differences) as shares of the caps."""
    traj = plan.trajectory
    assert traj is not None
    t, q = traj.t, traj.q
    dt = np.diff(t)
    qd = np.diff(q, axis=0) / dt[:, None]
    tm = 0.5 * (t[1:] + t[:-1])
    qdd = np.diff(qd, axis=0) / np.diff(tm)[:, None]
    qddd = np.diff(qdd, axis=0) / np.diff(0.5 * (tm[1:] + tm[:-1]))[:, None]
    return (
        float(np.max(np.abs(qd) / limits.max_joint_speed)),
        float(np.max(np.abs(qdd) / limits.max_joint_accel)),
        float(np.max(np.abs(qddd)) / jerk_cap),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bins", type=int, default=6)
    parser.add_argument("--parts", type=int, default=10)
    parser.add_argument("--seed", type=int, default=5200)
    parser.add_argument("--jerk-factor", type=float, default=2.0)
    args = parser.parse_args()
    cell = load_cell(CELL)
    library = default_part_library()
    limits = SafetyLimits.from_cell(cell)
    base = TimingOptions()
    variants = {
        "trapezoid (before)": TimingOptions(method="trapezoid"),
        "ruckig (after)": base,
        "ruckig, no blends": replace(base, blend=False),
        f"ruckig, jerk x{args.jerk_factor:g}": replace(base, jerk_rad_s3=base.jerk_rad_s3 * args.jerk_factor),
    }
    print("# bench_cycle")
    print(
        f"cell {CELL}: caps {cell.motion.joint_velocity[0]:g} rad/s, {cell.motion.joint_acceleration[0]:g} rad/s^2, "
        f"jerk {base.jerk_rad_s3:g} rad/s^3 (planner default), TCP {cell.motion.tcp_speed_m_s:g} m/s and "
        f"{cell.motion.tcp_acceleration_m_s2:g} m/s^2 on lines; {args.bins} bins of {args.parts} parts"
    )
    print(f"load average before: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")
    rows: dict[str, list[tuple[float, float, float, float, float, float]]] = {k: [] for k in variants}
    for b in range(args.bins):
        source = SyntheticBinSource(cell, count=args.parts, seed=args.seed + b, validate_physics=False, library=library)
        frame = source.capture()
        result = perceive(frame, source.ground_truth_segmenter(), library, PipelineOptions())
        line = []
        for name, timing in variants.items():
            plan = plan_pick(result.fits, result.normpositions, cell, PlanOptions(timing=timing))
            if plan.status != "ok" or plan.trajectory is None:
                line.append(f"{name}: {plan.status}")
                continue
            check_plan(parse_plan(plan.to_json()), limits)  # raises SafetyViolation: nothing would be sent
            v, a, j = cap_shares(plan, limits, base.jerk_rad_s3)
            dev = line_deviation_mm(plan, cell)
            rows[name].append((plan.trajectory.duration_s, v, a, j, dev, plan.timing_ms.get("timing", 0.0)))
            line.append(f"{name}: {plan.trajectory.duration_s:.2f} s")
        print(f"bin {b} (seed {args.seed + b}): " + ", ".join(line))
    print("\n## Cycle (plan trajectory duration) and checks, per variant")
    print(
        "| timing | plans | median s | max s | max speed / cap | max accel / cap | max jerk / default cap | "
        "max line deviation mm | timing ms (median) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, rs in rows.items():
        if not rs:
            print(f"| {name} | 0 | - | - | - | - | - | - | - |")
            continue
        r = np.array(rs)
        print(
            f"| {name} | {len(rs)} | {np.median(r[:, 0]):.2f} | {r[:, 0].max():.2f} | {r[:, 1].max():.3f} | "
            f"{r[:, 2].max():.3f} | {r[:, 3].max():.2f} | {r[:, 4].max():.3f} | {np.median(r[:, 5]):.1f} |"
        )
    print("every plan passed execution.plan.check_plan (SafetyLimits.from_cell) on its plan.json")
    print(f"load average after: {' / '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
