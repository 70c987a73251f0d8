"""Leaned grasps (`grasp.lean`): copies only of blocked top-down grasps, clear of the cell; slides bounded by the
part."""

from __future__ import annotations

import numpy as np

from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.grasp import lean
from normpos_grasp.records.grasp import GraspCandidate


def _candidate(world_from_tcp: np.ndarray, target: int = 0, opening: float = 0.05) -> GraspCandidate:
    return GraspCandidate(target, "p", "g", "synthesized", "parallel", world_from_tcp, opening, 0.05, 0.05, 1.0)


def _down(x: float = 0.5, y: float = 0.0, z: float = 0.03) -> np.ndarray:
    """Straight down (TCP z), the jaws closing along world y (TCP x), the pads' width along world x (TCP y)."""
    return make_pose(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]), [x, y, z])


def _wall_at(x_wall: float):  # type: ignore[no-untyped-def]
    """blocked(): a stand-in for the tool's boxes against a wall at world x >= x_wall: a 75 mm wide body whose
    bottom is 49 mm behind the TCP (the 2F-85's palm) overlaps the wall."""

    def blocked(poses: np.ndarray, openings: np.ndarray) -> np.ndarray:
        corners = np.array([[sx * 0.0625, sy * 0.0375, -0.049, 1.0] for sx in (-1, 1) for sy in (-1, 1)])
        world = np.einsum("nij,kj->nki", poses, corners)[..., :3]
        return world[..., 0].max(axis=1) >= x_wall

    return blocked


def test_copies_only_of_blocked_top_down_grasps() -> None:
    blocked = _wall_at(0.53)
    down = _candidate(_down())  # palm reaches x = 0.5375: blocked
    side = _candidate(make_pose(rotation_from_rotvec([0.0, -np.pi / 2, 0.0]), [0.5, 0.0, 0.03]))  # approach -x
    assert blocked(np.stack([side.world_from_tcp]), np.array([0.05]))[0]  # blocked too, but a side grasp
    free = _candidate(_down(x=0.4))  # palm reaches x = 0.4375: clear
    points = {0: np.array([[0.48, -0.04, 0.01], [0.52, 0.04, 0.05]])}
    copies = lean.wall_leans([down, side, free], blocked, None, None, points)
    assert copies and any("@lean" in c.grasp_id for c in copies)
    assert all(c.grasp_id.startswith("g@") for c in copies)
    sources = {id(c) for c in (down, side, free)}
    assert not any(id(c) in sources for c in copies)
    for c in copies:  # each a copy of `down`: from above, clear of the wall, the jaws closing along the same line
        assert -c.world_from_tcp[2, 2] >= np.cos(lean.LeanOptions().max_from_down_rad)
        assert not blocked(np.stack([c.world_from_tcp]), np.array([c.opening_m]))[0]
        assert abs(abs(c.world_from_tcp[:3, 0] @ down.world_from_tcp[:3, 0]) - 1.0) < 1e-9
    assert lean.wall_leans([side], blocked, None, None, points) == []  # side grasps get no copies
    assert lean.wall_leans([free], blocked, None, None, points) == []  # nor grasps the cell does not block


def test_slides_stay_over_the_part() -> None:
    # a wall that blocks unless the TCP moves along its y axis by more than 15 mm (slides only: no lean clears it)
    def blocked(poses: np.ndarray, openings: np.ndarray) -> np.ndarray:
        return (np.abs(poses[:, 0, 3] - 0.5) < 0.015) | (np.abs(poses[:, 2, 2] + 1.0) > 1e-9)

    c = _candidate(_down())
    # the part 70 mm long along the slide (world x): 20 and 30 mm slides keep the TCP 5 mm inside it, both ways
    long_part = {0: np.array([[0.465, -0.02, 0.01], [0.535, 0.02, 0.05]])}
    copies = lean.wall_leans([c], blocked, None, None, long_part)
    slid = sorted(round(float(k.world_from_tcp[0, 3]) - 0.5, 6) for k in copies)
    assert slid == [-0.03, -0.02, 0.02, 0.03] and all("@slide" in k.grasp_id for k in copies)
    # a part 40 mm long: no slide leaves the TCP 5 mm inside it, so no copy
    short_part = {0: np.array([[0.48, -0.02, 0.01], [0.52, 0.02, 0.05]])}
    assert lean.wall_leans([c], blocked, None, None, short_part) == []
    assert lean.wall_leans([c], blocked) == []  # without the part's points: no slides
