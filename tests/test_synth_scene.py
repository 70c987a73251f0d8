"""Scene composition: deterministic MuJoCo drops, no interpenetration, parts inside the container."""

from __future__ import annotations

import mujoco  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import pytest
import trimesh

import normpos_grasp.sim  # noqa: F401  (sets MUJOCO_GL=egl before mujoco loads)
from normpos_grasp.errors import InputError
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.scene import SceneOptions, compose_scene, static_boxes

LIB = default_part_library()


@pytest.fixture(scope="module")
def bin_layout():
    return compose_scene(SceneOptions(count=10, seed=7), LIB)


def test_same_seed_same_layout(bin_layout) -> None:
    again = compose_scene(SceneOptions(count=10, seed=7), LIB)
    assert again.part_names == bin_layout.part_names
    assert np.array_equal(again.world_from_object, bin_layout.world_from_object)
    other = compose_scene(SceneOptions(count=10, seed=8), LIB)
    assert not np.allclose(other.world_from_object, bin_layout.world_from_object)


def test_poses_are_rigid_and_inside_the_bin(bin_layout) -> None:
    opts = bin_layout.options
    half = np.asarray(opts.bin_inner_size_m) / 2
    assert bin_layout.n_parts == 10
    for k in range(bin_layout.n_parts):
        pose = bin_layout.world_from_object[k]
        np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
        verts = bin_layout.part_mesh_world(k).vertices
        assert np.all(np.abs(verts[:, :2]) <= half + 1e-3), f"part {k} pokes through a bin wall"
        assert verts[:, 2].min() >= opts.bin_floor_thickness_m - 1e-3, f"part {k} sinks into the floor"


def test_no_interpenetration(bin_layout) -> None:
    """Exact mesh-mesh check (FCL): parts may touch but not overlap by more than 0.5 mm."""
    manager = trimesh.collision.CollisionManager()
    for k in range(bin_layout.n_parts):
        manager.add_object(f"p{k}", bin_layout.templates[k].mesh, transform=bin_layout.world_from_object[k])
    hit, contacts = manager.in_collision_internal(return_data=True)
    depths = [c.depth for c in contacts] if hit else [0.0]
    assert max(depths) < 5e-4, f"parts overlap by {max(depths) * 1000:.2f} mm"
    assert bin_layout.max_penetration_m < 5e-4


def test_settles_on_table_and_conveyor() -> None:
    for container in ("table", "conveyor"):
        layout = compose_scene(SceneOptions(count=6, container=container, seed=3), LIB)
        floor = 0.0 if container == "table" else layout.options.conveyor_height_m
        lowest = min(layout.part_mesh_world(k).vertices[:, 2].min() for k in range(layout.n_parts))
        assert lowest == pytest.approx(floor, abs=1e-3)
        names = [b[0] for b in layout.static_boxes]
        assert names[0] == "table" and (container == "table") == (len(names) == 1)


def test_static_boxes_describe_the_bin() -> None:
    opts = SceneOptions(bin_inner_size_m=(0.5, 0.3), bin_wall_thickness_m=0.02, bin_wall_height_m=0.1)
    boxes = {name: (pose, size) for name, pose, size in static_boxes(opts)}
    pose, size = boxes["table"]
    assert pose[2, 3] + size[2] / 2 == pytest.approx(0.0)  # table top at z = 0
    pose, size = boxes["bin_wall_px"]
    assert pose[0, 3] - size[0] / 2 == pytest.approx(0.25)  # inner face of the +x wall
    assert pose[2, 3] + size[2] / 2 == pytest.approx(opts.bin_floor_thickness_m + 0.1)


def test_part_selection_and_validation() -> None:
    layout = compose_scene(SceneOptions(parts=("ring", "bracket"), count=4, seed=1), LIB)
    assert set(layout.part_names) <= {"ring", "bracket"}
    with pytest.raises(InputError, match="unknown part"):
        compose_scene(SceneOptions(parts=("widget",), count=1), LIB)
    with pytest.raises(InputError, match="container"):
        SceneOptions(container="shelf")
    with pytest.raises(InputError, match="clutter"):
        SceneOptions(clutter=1.5)
    assert compose_scene(SceneOptions(count=0), LIB).n_parts == 0


def test_parts_that_fall_off_the_table_are_left_out() -> None:
    layout = compose_scene(SceneOptions(count=5, container="table", table_size_m=(0.06, 0.06), seed=1), LIB)
    assert layout.n_parts < 5
    assert all(layout.world_from_object[k][2, 3] > -0.02 for k in range(layout.n_parts))
