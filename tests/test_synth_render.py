"""Renderer: depth vs analytic ray-plane / ray-sphere (0.1 mm), masks vs depth, MuJoCo vs ray casting."""

from __future__ import annotations

import mujoco  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import pytest
import trimesh  # noqa: F401  (a hard dependency: imported, never skipped)

import normpos_grasp.sim  # noqa: F401  (sets MUJOCO_GL=egl before mujoco loads)
from normpos_grasp.camera.model import Camera
from normpos_grasp.geometry.transforms import make_pose, rotation_from_rotvec
from normpos_grasp.sim.cameras import camera_pose
from normpos_grasp.sim.parts import default_part_library, part_library_by_name
from normpos_grasp.sim.render import Rendering, make_renderer, opengl_available
from normpos_grasp.sim.scene import SceneLayout, SceneOptions, compose_scene, static_boxes

BACKENDS = ["raycast", pytest.param("mujoco", marks=pytest.mark.skipif(not opengl_available(), reason="no OpenGL"))]
# off-centre principal point and fx != fy so the projection set-up is really exercised
K = np.array([[600.0, 0.0, 301.3], [0.0, 590.0, 228.7], [0.0, 0.0, 1.0]])
W, H = 320, 240


def _camera(pose: np.ndarray) -> Camera:
    return Camera(K * np.array([[0.5], [0.5], [1.0]]), W, H, world_from_camera=pose)


def _rays_world(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    xy = cam.pixel_grid_rays()
    dirs_c = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=-1)
    wfc = cam.require_world_from_camera()
    return wfc[:3, 3], dirs_c @ wfc[:3, :3].T  # direction with unit camera-z component


def _render(layout: SceneLayout, cam: Camera, backend: str) -> Rendering:
    r = make_renderer(layout, cam.width, cam.height, backend)
    try:
        return r.render(cam)
    finally:
        r.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_plane_depth_matches_analytic(backend: str) -> None:
    layout = SceneLayout((), np.zeros((0, 4, 4)), static_boxes(SceneOptions(container="table", table_size_m=(6, 6))))
    cam = _camera(camera_pose([0.05, -0.02, 0.0], 0.9, 35.0, 60.0, 7.0))
    out = _render(layout, cam, backend)
    origin, dirs = _rays_world(cam)
    t = -origin[2] / dirs[..., 2]  # ray parameter = z-depth because dirs have unit camera z
    hit = out.depth_m > 0
    assert hit.mean() > 0.99
    err = np.abs(out.depth_m[hit] - t[hit])
    assert err.max() < 1e-4, f"plane depth off by {err.max() * 1000:.4f} mm"
    assert np.all(out.instance_ids == 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sphere_depth_matches_analytic(backend: str) -> None:
    sphere = part_library_by_name()["sphere"]
    r = 0.0225
    pose = make_pose(rotation_from_rotvec([0.3, -0.2, 0.5]), [0.01, 0.02, r])
    layout = SceneLayout((sphere,), pose[None], static_boxes(SceneOptions(container="table")))
    cam = _camera(camera_pose([0.01, 0.02, r], 0.35, 25.0, 200.0))
    out = _render(layout, cam, backend)
    origin, dirs = _rays_world(cam)
    oc = origin - pose[:3, 3]
    a = np.einsum("hwc,hwc->hw", dirs, dirs)
    b = 2 * dirs @ oc
    c = oc @ oc - r * r
    disc = b * b - 4 * a * c
    inside = disc > 0
    t = np.where(inside, (-b - np.sqrt(np.where(inside, disc, 0))) / (2 * a), 0.0)
    # incidence angle below 60 degrees keeps the check away from the silhouette (tessellation chords)
    p = origin + t[..., None] * dirs
    n = (p - pose[:3, 3]) / r
    cos = -np.einsum("hwc,hwc->hw", n, dirs) / np.sqrt(a)
    core = inside & (cos > 0.5)
    assert core.sum() > 500
    assert np.all(out.instance_ids[core] == 1)
    err = np.abs(out.depth_m[core] - t[core])
    assert err.max() < 1e-4, f"sphere depth off by {err.max() * 1000:.4f} mm"
    # visible mask = full mask for an unoccluded part, and it covers the analytic disc
    assert np.array_equal(out.masks[0], out.masks_visible[0])
    assert out.masks_visible[0][core].all()
    assert out.visib_fractions[0] == 1.0


@pytest.fixture(scope="module")
def clutter() -> tuple[SceneLayout, Camera]:
    layout = compose_scene(SceneOptions(count=10, seed=11, clutter=0.8, stack_layers=3), default_part_library())
    cam = _camera(camera_pose(layout.container_centre(), 0.55, 30.0, 120.0))
    return layout, cam


@pytest.mark.parametrize("backend", BACKENDS)
def test_masks_agree_with_depth(clutter: tuple[SceneLayout, Camera], backend: str) -> None:
    layout, cam = clutter
    out = _render(layout, cam, backend)
    assert out.backend == backend
    origin, dirs = _rays_world(cam)
    ids = out.instance_ids
    assert set(np.unique(ids)) <= set(range(layout.n_parts + 1))
    for k in range(layout.n_parts):
        vis, full = out.masks_visible[k], out.masks[k]
        assert np.array_equal(vis, ids == k + 1)
        assert not np.any(vis & ~full), "visible pixels must lie inside the full mask"
        if not vis.any():
            continue
        # the depth of every visible pixel is where that pixel's ray first meets part k
        mesh = layout.part_mesh_world(k)
        vv, uu = np.nonzero(vis)
        sel = np.linspace(0, len(vv) - 1, min(len(vv), 200)).astype(int)
        locs, idx, _ = mesh.ray.intersects_location(
            np.repeat(origin[None], len(sel), axis=0), dirs[vv[sel], uu[sel]], multiple_hits=False
        )
        assert len(idx) >= 0.97 * len(sel), "visible pixels whose ray misses the part"
        z = (locs - origin) @ cam.require_world_from_camera()[:3, 2]
        err = np.abs(out.depth_m[vv[sel][idx], uu[sel][idx]] - z)
        assert np.median(err) < 1e-5 and np.percentile(err, 95) < 1e-4
        # hidden pixels of the full mask lie behind the drawn surface
        hidden = full & ~vis
        if hidden.any():
            assert np.all(out.depth_m[hidden] > 0)
    assert (out.masks.sum(axis=0) >= 1)[ids > 0].all()


def test_backends_agree(clutter: tuple[SceneLayout, Camera]) -> None:
    if not opengl_available():
        pytest.skip("no OpenGL: only the ray-cast backend can run")
    layout, cam = clutter
    a = _render(layout, cam, "mujoco")
    b = _render(layout, cam, "raycast")
    both = (a.depth_m > 0) & (b.depth_m > 0)
    assert np.median(np.abs(a.depth_m - b.depth_m)[both]) < 1e-6
    assert (a.instance_ids == b.instance_ids).mean() > 0.998
    assert (a.masks == b.masks).mean() > 0.999
    np.testing.assert_allclose(a.visib_fractions, b.visib_fractions, atol=0.03)


def test_auto_falls_back_to_ray_casting_without_opengl(monkeypatch: pytest.MonkeyPatch) -> None:
    from normpos_grasp.errors import SimulationError
    from normpos_grasp.sim import render as render_mod

    monkeypatch.setattr(render_mod, "_GL_CONTEXT", None)
    monkeypatch.setattr(render_mod, "_GL_FAILED", "no OpenGL in this test")
    layout = SceneLayout((), np.zeros((0, 4, 4)), static_boxes(SceneOptions(container="table")))
    assert not render_mod.opengl_available()
    assert isinstance(render_mod.make_renderer(layout, W, H, "auto"), render_mod.RaycastSceneRenderer)
    with pytest.raises(SimulationError, match="no OpenGL"):
        render_mod.make_renderer(layout, W, H, "mujoco")


def test_distorted_or_unposed_cameras_are_refused() -> None:
    from normpos_grasp.errors import InputError
    from normpos_grasp.sim.render import render

    layout = SceneLayout((), np.zeros((0, 4, 4)), static_boxes(SceneOptions(container="table")))
    pose = camera_pose([0, 0, 0], 0.5, 0.0, 0.0)
    with pytest.raises(InputError, match="distortion"):
        render(layout, Camera(K, 640, 480, np.array([0.1, 0, 0, 0, 0]), world_from_camera=pose), "raycast")
    with pytest.raises(InputError, match="world_from_camera"):
        render(layout, Camera(K, 640, 480), "raycast")
