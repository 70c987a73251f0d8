"""Compile and store everything a fresh install would otherwise pay for in its first pick (`make install` runs it).

- the fit kernels (numba, cached on disk) and the stored preparations of the built-in and example templates
  (`templates.warmup`);
- the compiled one-pose inverse kinematics (`kinematics.analytic_ik`, numba, cached on disk), which the planner and
  the loopback controller call;
- the compiled box tests of the planner's cell screen (`collision.obb`) and its bounding-sphere proofs
  (`collision.spheres`), numba, cached on disk.

    python -m normpos_grasp.warmup
"""

from __future__ import annotations

import logging
import time

import numpy as np

from normpos_grasp.collision.obb import aligned_box_hits, obb_overlap_pairs
from normpos_grasp.collision.spheres import spheres_apart, spheres_off_boxes
from normpos_grasp.kinematics.robot import Robot
from normpos_grasp.kinematics.ur_params import ur_params
from normpos_grasp.templates.warmup import prepare_builtin, warm_up

logger = logging.getLogger(__name__)


def warm_up_kinematics() -> float:
    """Solve one pose per UR model so the compiled IK is built and cached; returns the seconds it took."""
    t0 = time.perf_counter()
    for name in ("ur3e", "ur5e", "ur10e", "ur16e", "ur20", "ur30"):
        robot = Robot(ur_params(name))
        q = np.array([0.3, -1.2, 1.4, -1.7, -1.5, 0.2])
        solutions = robot.ik(robot.fk(q), q)
        if len(solutions) == 0:
            raise RuntimeError(f"IK warm-up found no solution for {name} at a regular pose")
    return time.perf_counter() - t0


def warm_up_collision() -> float:
    """Run the compiled box-pair tests and sphere proofs once so they are built and cached; returns the seconds it
    took."""
    t0 = time.perf_counter()
    eye = np.eye(3)[None]
    if not obb_overlap_pairs(np.zeros((1, 3)), eye, np.ones(3), np.zeros((1, 3)), eye, np.ones((1, 3)))[0]:
        raise RuntimeError("box test warm-up: two boxes at one centre reported apart")
    if not aligned_box_hits(np.eye(4)[None], np.ones(3), np.zeros((1, 3)), eye, np.ones((1, 3)))[0]:
        raise RuntimeError("box screen warm-up: two boxes at one centre reported apart")
    centre = np.zeros((1, 1, 3))
    if spheres_off_boxes(centre, np.ones((1, 1)), -np.ones((1, 3)), np.ones((1, 3)), np.zeros(1, dtype=bool), -1)[0]:
        raise RuntimeError("sphere proof warm-up: a sphere inside a box reported clear")
    if spheres_apart(
        centre, np.ones(1), np.zeros((1, 1), dtype=bool), np.zeros(1, dtype=np.int64), centre, np.ones((1, 1))
    )[0]:
        raise RuntimeError("sphere proof warm-up: two spheres at one centre reported apart")
    return time.perf_counter() - t0


def main() -> None:
    warm_up()  # logs its own time
    prepare_builtin()
    logger.info("inverse kinematics ready in %.1f s", warm_up_kinematics())
    logger.info("collision box test ready in %.1f s", warm_up_collision())


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main()
