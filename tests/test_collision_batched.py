"""CollisionWorld's one-pass sphere proof of an empty-handed approach and a held lift (`configs_clear(held_rows=...)`)
agrees with the two scoped passes it replaces, and the tool check without its numpy pre-test finds the same hits."""

from __future__ import annotations

import numpy as np
import trimesh

from normpos_grasp.collision import CollisionWorld, tool_from_gripper
from normpos_grasp.geometry import make_pose
from normpos_grasp.kinematics import Gripper
from normpos_grasp.planning import ArmModel
from normpos_grasp.typing import FloatArray

DOWN = np.diag([1.0, -1.0, -1.0])


def _world() -> tuple[CollisionWorld, ArmModel, trimesh.Trimesh]:
    world = CollisionWorld()
    arm = ArmModel.from_name("ur5e", make_pose(np.diag([-1.0, -1.0, 1.0]), [-0.5, 0.0, 0.0]))
    world.add_box("table", make_pose(None, [0, 0, -0.025]), [1.2, 1.2, 0.05], "cell")
    world.add_box("wall", make_pose(None, [0.25, 0, 0.1]), [0.02, 0.5, 0.2], "cell")
    cube = trimesh.creation.box((0.05, 0.05, 0.05))
    world.add_mesh("object/0", cube, make_pose(None, [0.0, 0.0, 0.025]), "object")
    world.add_mesh("object/1", cube, make_pose(None, [0.15, 0.0, 0.025]), "object")
    world.add_points("clutter/3", np.array([[-0.1, 0.1, 0.01], [-0.1, 0.1, 0.015]]), 0.01)
    world.set_arm(arm)
    world.set_tool(tool_from_gripper(Gripper.load("2f85")))
    return world, arm, cube


def test_held_rows_match_the_scoped_passes() -> None:
    world, arm, cube = _world()
    rng = np.random.default_rng(3)
    flange_from_tcp = world.tool.flange_from_tcp  # type: ignore[union-attr]
    n_clear = 0
    for _ in range(40):
        # five TCP poses over and into the part field: some proven clear, some not
        xyz = rng.uniform([-0.15, -0.15, 0.03], [0.15, 0.15, 0.35], size=(5, 3))
        poses = np.stack([make_pose(DOWN, p) for p in xyz])
        q, ok = arm.ik(poses @ np.linalg.inv(flange_from_tcp))
        branch = int(np.argmax(ok.all(axis=0)))
        if not ok[:, branch].all():
            continue
        qs = q[:, branch]
        tcp_from_object = np.linalg.inv(poses[2]) @ make_pose(None, [0.0, 0.0, 0.025])
        radius = float(np.linalg.norm(cube.vertices, axis=1).max())
        rows = np.array([False, False, False, True, True])
        one = world.configs_clear(qs, 0.06, rows, tcp_from_object, "object/0", radius)
        empty = world.configs_clear(qs[:3], 0.06)
        with world.holding("object/0", cube, tcp_from_object):
            held = world.configs_clear(qs[3:], 0.06)
        assert one.tolist() == np.concatenate([empty, held]).tolist()
        n_clear += int(one.sum())
        # what the spheres prove clear, fcl finds clear
        for p in np.flatnonzero(one[:3]):
            assert world.check_config(qs[p], 0.06) is None
    assert n_clear > 0


def test_tool_check_finds_the_same_first_hit_on_every_shape() -> None:
    world, _, _ = _world()
    # the jaws straddle object/0 (free), close on it (object), sink into the table (cell), reach the wall (cell)
    assert world.check_tool(make_pose(DOWN, [0.0, 0.0, 0.04]), 0.085) is None
    hit = world.check_tool(make_pose(DOWN, [0.0, 0.0, 0.04]), 0.03)
    assert hit is not None and hit.reason == "collision_object"
    hit = world.check_tool(make_pose(DOWN, [0.0, 0.3, -0.005]), 0.085)
    assert hit is not None and hit.reason == "collision_cell"
    with world.without("object/0", "object/1"):
        assert world.check_tool(make_pose(DOWN, [0.0, 0.0, 0.04]), 0.03) is None
    # far from everything: no shape is near, nothing is hit
    assert world.check_tool(make_pose(DOWN, [0.0, 0.0, 1.5]), 0.03) is None


def _rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


def obb_overlap(
    c1: FloatArray, r1: FloatArray, h1: FloatArray, c2: FloatArray, r2: FloatArray, h2: FloatArray
) -> FloatArray:
    """The reference for the compiled box tests: the separating-axis test of oriented boxes in numpy, broadcast
    over leading axes: centres (..., 3), rotations (..., 3, 3) (columns = box axes), half extents (..., 3).
    Returns (...,) bool: True where the boxes overlap."""
    rot = np.einsum("...ji,...jk->...ik", r1, r2)  # r1^T r2
    t = np.einsum("...ji,...j->...i", r1, c2 - c1)  # in box 1's frame
    abs_rot = np.abs(rot) + 1e-12
    sep = np.zeros(np.broadcast_shapes(t.shape[:-1], h2.shape[:-1], h1.shape[:-1]), dtype=bool)
    for i in range(3):  # box 1 axes
        ra = h1[..., i]
        rb = np.einsum("...j,...j->...", h2, abs_rot[..., i, :])
        sep |= np.abs(t[..., i]) > ra + rb
    for j in range(3):  # box 2 axes
        ra = np.einsum("...i,...i->...", h1, abs_rot[..., :, j])
        rb = h2[..., j]
        sep |= np.abs(np.einsum("...i,...i->...", t, rot[..., :, j])) > ra + rb
    for i in range(3):  # cross products
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            ra = h1[..., i1] * abs_rot[..., i2, j] + h1[..., i2] * abs_rot[..., i1, j]
            rb = h2[..., j1] * abs_rot[..., i, j2] + h2[..., j2] * abs_rot[..., i, j1]
            dist = np.abs(t[..., i2] * rot[..., i1, j] - t[..., i1] * rot[..., i2, j])
            sep |= dist > ra + rb
    return ~sep


def test_compiled_box_pairs_match_the_numpy_separating_axis_test() -> None:
    from normpos_grasp.collision.obb import obb_overlap_pairs

    rng = np.random.default_rng(21)
    n = 4000
    h1 = np.array([0.01, 0.0135, 0.031])  # a finger
    c1 = rng.uniform(-0.06, 0.06, size=(n, 3))
    r1 = _rotations(rng, n)
    c2 = rng.uniform(-0.02, 0.02, size=(n, 3))
    r2 = np.where(rng.random(n)[:, None, None] < 0.5, np.eye(3), _rotations(rng, n))  # cell boxes: mostly aligned
    h2 = rng.uniform(0.005, 0.04, size=(n, 3))
    # pairs just touching along a face normal: the verdict flips within rounding there
    c1[:200] = c2[:200] + r2[:200, :, 0] * (h2[:200, :1] + h1[0] - 1e-12)
    r1[:200] = r2[:200]
    expected = obb_overlap(c1, r1, h1[None], c2, r2, h2)
    got = obb_overlap_pairs(c1, r1, h1, c2, r2, h2)
    assert got.dtype == bool and got.shape == (n,)
    assert 0.1 * n < expected.sum() < 0.9 * n  # both verdicts well represented
    np.testing.assert_array_equal(got, expected)


def test_tool_box_screen_agrees_with_fcl_on_the_cell_boxes() -> None:
    world, _, _ = _world()
    rng = np.random.default_rng(5)
    xyz = rng.uniform([-0.2, -0.2, 0.0], [0.35, 0.2, 0.25], size=(300, 3))
    poses = np.stack([make_pose(DOWN, p) for p in xyz])
    openings = rng.uniform(0.0, 0.085, size=300)
    hits = world.tool_box_hits(poses, openings)
    assert 20 < hits.sum() < 280
    for pose, opening, hit in zip(poses, openings, hits, strict=True):
        if hit:  # a box of the tool overlaps a cell box: fcl finds the same contact with the cell
            found = world.check_tool(pose, float(opening), skip=("object", "clutter"))
            assert found is not None and found.reason == "collision_cell"


def test_compiled_aligned_screen_matches_the_aabb_test_then_the_numpy_pairs() -> None:
    from normpos_grasp.collision.obb import aligned_box_hits

    rng = np.random.default_rng(22)
    n = 3000
    half = np.array([0.01, 0.0135, 0.031])
    world = np.repeat(np.eye(4)[None], n, axis=0)
    world[:, :3, :3] = _rotations(rng, n)
    world[:, :3, 3] = rng.uniform(-0.15, 0.15, size=(n, 3))
    bc = np.array([[0.0, 0.0, -0.025], [0.12, 0.0, 0.05], [-0.12, 0.0, 0.05]])  # a floor and two walls
    bh = np.array([[0.15, 0.15, 0.025], [0.01, 0.15, 0.05], [0.01, 0.15, 0.05]])
    br = np.repeat(np.eye(3)[None], 3, axis=0)
    ext = (np.abs(world[:, :3, :3]) * half).sum(axis=2)
    ii, bb = np.nonzero(np.all(np.abs(world[:, None, :3, 3] - bc[None]) <= bh[None] + ext[:, None] + 1e-9, axis=2))
    expected = np.zeros(n, dtype=bool)
    expected[ii[obb_overlap(world[ii, :3, 3], world[ii, :3, :3], half[None], bc[bb], br[bb], bh[bb])]] = True
    got = aligned_box_hits(world, half, bc, br, bh)  # the AABB extents summed inside, in numpy's order
    assert 0.1 * n < expected.sum() < 0.9 * n
    assert (np.isin(np.arange(n), ii) & ~expected).any()  # some pairs pass the AABB test and still stay apart
    np.testing.assert_array_equal(got, expected)
