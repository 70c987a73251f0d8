"""Calibration of the grip-mechanics prediction (`normpos_grasp.grasp.quality`) against MuJoCo outcomes.

    .venv/bin/python benchmarks/bench_grasp_quality.py [--scenes 6] [--count 6] [--seed 100] [--per-part 6]

Bins of physics-settled parts in the packaged UR5e cell; for every part (true pose, so that only the grip is
judged), the planner's reachable, collision-free parallel candidates (mechanics check off) are scored by the
mechanics model and replayed in MuJoCo (`sim.physics.validate_grasp`) on that part alone on the bin floor, up to
`--per-part` per part spread over the mechanics margin. Prints, per margin bin, the predicted success
(`CALIBRATION`) against the observed share held, the rejected grasps' observed success by reason, and the machine
load. `--fit` prints the observed success per bin to paste into `CALIBRATION` (fit on seeds other than the ones
you report).
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from dataclasses import replace

import numpy as np

from normpos_grasp.cell.config import resolve_cell
from normpos_grasp.grasp.candidates import candidates_for_object
from normpos_grasp.grasp.quality import CALIBRATION, judge
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.loop import _physics_gripper
from normpos_grasp.planning.evaluate import EvaluationOptions, evaluate_candidates
from normpos_grasp.planning.plan import PlanOptions
from normpos_grasp.records.plan import Target
from normpos_grasp.sim.cell_scene import compose_cell_scene
from normpos_grasp.sim.physics import PhysicsOptions, validate_grasp


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--count", type=int, default=6)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--per-part", type=int, default=6)
    parser.add_argument("--fit", action="store_true", help="print the observed success per bin for CALIBRATION")
    args = parser.parse_args()
    from normpos_grasp.collision.world import CollisionWorld

    cell = resolve_cell("ur5e_bin_parallel")
    arm = ArmModel.from_name(cell.robot_model, cell.world_from_base)
    gripper = _physics_gripper(cell)
    opts = PlanOptions()
    cand_opts = replace(
        opts.candidates, synthesis=replace(opts.candidates.synthesis, finger_tip_m=cell.tool.finger_depth_m)
    )
    walls = cell.bin.world_from_bin[:3, :2].T.copy() if cell.bin is not None else None
    ev_opts = replace(EvaluationOptions(), mechanics=None, max_feasible=0, max_feasible_per_target=0)
    rows: list[tuple[float, bool, str, bool, str]] = []  # (margin, mechanics ok, reason, held, part)
    misjudged: list[str] = []
    t0 = time.perf_counter()
    for s in range(args.scenes):
        layout = compose_cell_scene(cell, args.count, args.seed + s)
        for i, tmpl in enumerate(layout.templates):
            pose = layout.world_from_object[i]
            world = CollisionWorld()
            for box in cell.static_boxes:
                world.add_box(box.name, box.world_from_box, box.size, "cell")
            world.add_mesh("object/0", tmpl.mesh, pose, "object")
            world.set_arm(arm)
            world.set_tool(cell.tool)
            world.update()
            centre = pose[:3, :3] @ np.asarray(tmpl.mesh.bounds).mean(axis=0) + pose[:3, 3]
            target = Target("object/0", pose, tmpl.mesh, float(centre[2]), tmpl.mass_kg, 0, tmpl.name)
            cands = candidates_for_object(0, tmpl, pose, "parallel", cand_opts, walls)
            result = evaluate_candidates(
                cands,
                [target],
                world,
                arm,
                np.asarray(cell.home_q),
                cell.entry_z,
                cell.lift_m,
                cell.entry_clearance_m,
                (cell.motion.workspace_min, cell.motion.workspace_max),
                ev_opts,
            )
            feasible = list(result.ranked)
            if not feasible:
                continue
            scored = []
            for ev in feasible:
                c = ev.candidate
                mech = judge(c.scheme, tmpl.mesh, tmpl.mass_kg, pose, c.world_from_tcp, cell.tool)
                scored.append((mech.margin if mech.ok else -1.0, mech, c))
            scored.sort(key=lambda x: x[0])
            picks = np.unique(np.linspace(0, len(scored) - 1, min(args.per_part, len(scored))).round().astype(int))
            for k in picks:
                margin, mech, c = scored[int(k)]
                res = validate_grasp(
                    tmpl,
                    pose,
                    [],
                    layout.static_boxes,
                    gripper,
                    c.world_from_tcp,
                    max(c.opening_m, 1e-3),
                    PhysicsOptions(lift_to_z_m=float(cell.entry_z) + PhysicsOptions().approach_m),
                )
                if res.outcome == "collision":
                    continue  # the hand hit the floor: not a question of the grip
                rows.append((margin, mech.ok, mech.reason, res.outcome == "held", tmpl.name))
                if mech.ok != (res.outcome == "held"):
                    misjudged.append(
                        f"  {tmpl.name} {c.grasp_id}: mechanics {mech.reason or 'ok'} (margin {margin:.2f}, area "
                        f"{mech.area_m2 * 1e6:.0f} mm^2, angle {np.degrees(mech.cone_angle_rad):.1f} deg), "
                        f"MuJoCo {res.outcome} {res.reason}"
                    )
    wall = time.perf_counter() - t0
    edges = [lo for lo, _ in CALIBRATION] + [1.0001]
    print(
        f"grasps replayed in MuJoCo: {len(rows)} ({args.scenes} scenes x {args.count} parts, seed {args.seed}), "
        f"{wall:.0f} s wall, load {os.getloadavg()[0]:.1f}"
    )
    print("margin bin     grasps  predicted  observed  diff (points)")
    worst = 0.0
    for b in range(len(CALIBRATION)):
        lo, hi = edges[b], edges[b + 1]
        held = [h for m, ok, _, h, _ in rows if ok and lo <= m < hi]
        if not held:
            print(f"[{lo:.2f}, {min(hi, 1.0):.2f})  {0:6d}  {CALIBRATION[b][1]:9.2f}         -")
            continue
        pred = CALIBRATION[b][1]
        obs = float(np.mean(held))
        worst = max(worst, abs(pred - obs) * 100)
        print(f"[{lo:.2f}, {min(hi, 1.0):.2f})  {len(held):6d}  {pred:9.2f}  {obs:8.2f}  {100 * (obs - pred):+6.1f}")
    print(f"largest gap over populated bins: {worst:.1f} points (target 5)")
    rejected: dict[str, list[bool]] = defaultdict(list)
    for _, ok, reason, held, _ in rows:
        if not ok:
            rejected[reason].append(held)
    for reason, held in sorted(rejected.items()):
        print(f"rejected by mechanics, {reason}: {len(held)} grasps, {np.mean(held):.2f} held in MuJoCo (predicted 0)")
    by_part: dict[str, list[bool]] = defaultdict(list)
    for _, ok, _, held, part in rows:
        if ok:
            by_part[part].append(held)
    print(
        "accepted grasps held, by part: "
        + ", ".join(f"{p} {np.mean(h):.2f} ({len(h)})" for p, h in sorted(by_part.items()))
    )
    if misjudged:
        print(f"misjudged ({len(misjudged)}):")
        print("\n".join(misjudged))
    if args.fit:
        fitted = []
        for b in range(len(CALIBRATION)):
            lo, hi = edges[b], edges[b + 1]
            held = [h for m, ok, _, h, _ in rows if ok and lo <= m < hi]
            fitted.append((lo, round(float(np.mean(held)), 2) if held else CALIBRATION[b][1]))
        print(f"CALIBRATION = {tuple(fitted)}")


if __name__ == "__main__":
    main()
