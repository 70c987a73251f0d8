"""Joint-space motion between two configurations: the straight joint path when it is collision-free, otherwise
RRT-Connect (bidirectional RRT with greedy connect) followed by shortcut smoothing. Deterministic for a given seed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from normpos_grasp.errors import PlanningError
from normpos_grasp.typing import FloatArray

ConfigFree = Callable[[FloatArray], bool]


@dataclass(frozen=True)
class MotionOptions:
    """resolution_rad: largest joint step between collision checks along an edge, rad. step_rad: RRT extension
    step, rad. max_iterations: RRT-Connect iterations before giving up. shortcut_iterations: random shortcut tries.
    seed: RNG seed."""

    resolution_rad: float = 0.03
    step_rad: float = 0.3
    max_iterations: int = 3000
    shortcut_iterations: int = 60
    seed: int = 0


def edge_free(a: FloatArray, b: FloatArray, free: ConfigFree, resolution: float) -> bool:
    """True when every configuration on the straight joint segment a -> b (sampled at `resolution` rad of the
    largest joint step, end point included, start excluded) is collision-free. When `free` has a `clear_batch`
    method ((K, 6) -> (K,) bool, True = certainly free, a conservative pre-test), only the other samples are
    checked one by one."""
    n = max(int(np.ceil(np.abs(b - a).max() / resolution)), 1)
    # coarse-to-fine order finds collisions in the middle of long edges early
    order = _bisection_order(n)
    clear_batch = getattr(free, "clear_batch", None)
    if clear_batch is not None:  # samples proven free in one vectorised pass skip the exact check
        ks = np.arange(1, n + 1)
        clear = np.asarray(clear_batch(a + (b - a) * (ks / n)[:, None]), dtype=bool)
        order = [k for k in order if not clear[k - 1]]
    return all(free(a + (b - a) * (k / n)) for k in order)


def _bisection_order(n: int) -> list[int]:
    seen: set[int] = set()
    out = [n]
    seen.add(n)
    step = n
    while step > 1:
        step = max(step // 2, 1)
        for k in range(step, n, step):
            if k not in seen:
                seen.add(k)
                out.append(k)
    for k in range(1, n):
        if k not in seen:
            out.append(k)
    return out


def plan_joint_motion(
    start: FloatArray,
    goal: FloatArray,
    free: ConfigFree,
    lower: FloatArray,
    upper: FloatArray,
    options: MotionOptions | None = None,
) -> list[FloatArray]:
    """Collision-free joint path [start, ..., goal] (list of (6,) rad). Raises PlanningError when the start or
    goal collides or RRT-Connect finds no path within `max_iterations`."""
    opts = options or MotionOptions()
    s = np.asarray(start, dtype=np.float64)
    g = np.asarray(goal, dtype=np.float64)
    if not free(s):
        raise PlanningError("joint motion: the start configuration is in collision")
    if not free(g):
        raise PlanningError("joint motion: the goal configuration is in collision")
    if edge_free(s, g, free, opts.resolution_rad):
        return [s, g]
    path = rrt_connect(s, g, free, lower, upper, opts)
    return shortcut(path, free, opts)


def rrt_connect(
    start: FloatArray, goal: FloatArray, free: ConfigFree, lower: FloatArray, upper: FloatArray, options: MotionOptions
) -> list[FloatArray]:
    """Bidirectional RRT with greedy connection (Kuffner and LaValle 2000)."""
    rng = np.random.default_rng(options.seed)
    trees: list[tuple[list[FloatArray], list[int]]] = [([start], [-1]), ([goal], [-1])]

    def nearest(nodes: list[FloatArray], q: FloatArray) -> int:
        arr = np.asarray(nodes)
        return int(np.argmin(np.abs(arr - q).max(axis=1)))

    def extend(tree: tuple[list[FloatArray], list[int]], q: FloatArray) -> tuple[str, int]:
        nodes, parents = tree
        k = nearest(nodes, q)
        d = q - nodes[k]
        dist = np.abs(d).max()
        new = q if dist <= options.step_rad else nodes[k] + d * (options.step_rad / dist)
        if not edge_free(nodes[k], new, free, options.resolution_rad):
            return "trapped", -1
        nodes.append(new)
        parents.append(k)
        return ("reached" if dist <= options.step_rad else "advanced"), len(nodes) - 1

    for it in range(options.max_iterations):
        sample = goal if it % 10 == 0 else rng.uniform(lower, upper)
        a, b = trees[it % 2], trees[(it + 1) % 2]
        status, new_idx = extend(a, sample)
        if status == "trapped":
            continue
        target = a[0][new_idx]
        while True:
            status_b, idx_b = extend(b, target)
            if status_b != "advanced":
                break
        if status_b == "reached":
            path_a = _trace(a, new_idx)
            path_b = _trace(b, idx_b)
            path = path_a[::-1] + path_b[1:]
            if it % 2 == 1:
                path = path[::-1]
            return path
    raise PlanningError(
        f"RRT-Connect found no collision-free joint path in {options.max_iterations} iterations; "
        "the goal may be enclosed, or raise MotionOptions.max_iterations"
    )


def _trace(tree: tuple[list[FloatArray], list[int]], idx: int) -> list[FloatArray]:
    nodes, parents = tree
    out = []
    while idx >= 0:
        out.append(nodes[idx])
        idx = parents[idx]
    return out


def shortcut(path: list[FloatArray], free: ConfigFree, options: MotionOptions) -> list[FloatArray]:
    """Random shortcutting: replace sub-paths by straight joint segments when those are collision-free."""
    rng = np.random.default_rng(options.seed + 1)
    pts = list(path)
    for _ in range(options.shortcut_iterations):
        if len(pts) <= 2:
            break
        i, j = sorted(rng.choice(len(pts), size=2, replace=False))
        if j - i < 2:
            continue
        if edge_free(pts[i], pts[j], free, options.resolution_rad):
            pts = pts[: i + 1] + pts[j:]
    return pts
