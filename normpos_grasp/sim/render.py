"""Render a `SceneLayout` through a `Camera`: RGB, metric depth, instance ids, full and visible masks.

Fast path: MuJoCo's offscreen OpenGL renderer (MUJOCO_GL=egl by default) with the projection set from the
camera's K exactly and the reversed-Z float depth buffer linearised in float64 (sub-micrometre agreement
with analytic surfaces). Fallback, chosen automatically when no OpenGL context can be made: ray casting with
trimesh (embree when installed). Full (amodal) masks come from ray casts of each part against pixels where
something nearer than the part's far side was drawn, so occluded parts get exact full masks cheaply.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import InputError, SimulationError
from normpos_grasp.geometry.transforms import invert_pose, transform_points
from normpos_grasp.sim.parts import PART_COLORS
from normpos_grasp.sim.scene import SceneLayout, build_mjcf, import_mujoco, load_model
from normpos_grasp.typing import BoolArray, FloatArray, UInt8Array

os.environ.setdefault("MUJOCO_GL", "egl")

if TYPE_CHECKING:
    import trimesh

logger = logging.getLogger(__name__)

BACKENDS = ("auto", "mujoco", "raycast")
_NEAR_M = 0.02
_FAR_M = 20.0


@dataclass(frozen=True, eq=False)
class Rendering:
    """Ideal (noise-free) images of one view.

    rgb: (H, W, 3) uint8. depth_m: (H, W) float64 z-depth in metres, 0 where no surface.
    instance_ids: (H, W) int32, 0 for background and static geometry, k + 1 for part k.
    masks: (N, H, W) bool full (amodal) silhouettes; masks_visible: (N, H, W) bool visible pixels.
    backend: 'mujoco' or 'raycast' (which renderer produced it).
    part_materials: material of each part (Template.material), for material-dependent sensor effects.
    """

    rgb: UInt8Array
    depth_m: FloatArray
    instance_ids: np.ndarray
    masks: BoolArray
    masks_visible: BoolArray
    backend: str
    part_materials: tuple[str, ...] = ()

    @property
    def visib_fractions(self) -> FloatArray:
        """(N,) visible / full pixel count per part (0 where the part is outside the image)."""
        n = len(self.masks)  # an empty scene has (0, H, W) masks: reshape(0, -1) is ambiguous
        full = self.masks.reshape(n, n and -1).sum(axis=1)
        vis = self.masks_visible.reshape(n, n and -1).sum(axis=1)
        return np.where(full > 0, vis / np.maximum(full, 1), 0.0)


# -- shared helpers --------------------------------------------------------------------------
def _pixel_rays(camera: Camera) -> FloatArray:
    """(H, W, 3) camera-frame ray directions with z = 1 through every pixel centre (pinhole, no distortion)."""
    return _rays_at(camera, *np.mgrid[0 : camera.height, 0 : camera.width])


def _rays_at(camera: Camera, v: np.ndarray, u: np.ndarray) -> FloatArray:
    """(..., 3) camera-frame directions with z = 1 through pixels (v, u) (pinhole, no distortion)."""
    out = np.empty(np.shape(u) + (3,))
    out[..., 0] = (u - camera.cx) / camera.fx
    out[..., 1] = (v - camera.cy) / camera.fy
    out[..., 2] = 1.0
    return out


_INTERSECTORS: dict[int, tuple[Any, Any]] = {}


def _intersector(mesh: trimesh.Trimesh) -> Any:
    """Cached ray-mesh intersector (embree when available) for a template mesh."""
    key = id(mesh)
    hit = _INTERSECTORS.get(key)
    if hit is not None and hit[0] is mesh:
        return hit[1]
    inter: Any
    try:
        from trimesh.ray import ray_pyembree

        inter = ray_pyembree.RayMeshIntersector(mesh)
    except ImportError:  # pragma: no cover - embree missing: pure-numpy triangle tests
        from trimesh.ray import ray_triangle

        inter = ray_triangle.RayMeshIntersector(mesh)
    if len(_INTERSECTORS) > 256:
        _INTERSECTORS.clear()
    _INTERSECTORS[key] = (mesh, inter)
    return inter


def _full_masks(layout: SceneLayout, camera: Camera, depth: FloatArray, ids: np.ndarray) -> BoolArray:
    """Amodal masks: visible pixels plus ray-cast hits where a nearer surface hides the part."""
    h, w = depth.shape
    n = layout.n_parts
    masks = np.zeros((n, h, w), dtype=bool)
    cfw = camera.camera_from_world
    for k in range(n):
        visible = ids == k + 1
        t = layout.templates[k]
        cfo = cfw @ layout.world_from_object[k]
        verts_c = transform_points(cfo, np.asarray(t.mesh.vertices))
        zmax = float(verts_c[:, 2].max())
        if zmax <= _NEAR_M:
            masks[k] = visible
            continue
        front = verts_c[verts_c[:, 2] > 1e-6]
        if len(front) < len(verts_c):
            u0, v0, u1, v1 = 0, 0, w, h
        else:
            uv = camera.project(front)
            u0 = int(np.clip(np.floor(uv[:, 0].min()) - 1, 0, w))
            u1 = int(np.clip(np.ceil(uv[:, 0].max()) + 2, 0, w))
            v0 = int(np.clip(np.floor(uv[:, 1].min()) - 1, 0, h))
            v1 = int(np.clip(np.ceil(uv[:, 1].max()) + 2, 0, h))
        if u1 <= u0 or v1 <= v0:
            masks[k] = visible
            continue
        sub_d = depth[v0:v1, u0:u1]
        cand = (~visible[v0:v1, u0:u1]) & (sub_d > 0) & (sub_d < zmax + 1e-6)
        full = visible.copy()
        if cand.any():
            vv, uu = np.nonzero(cand)
            dirs_c = _rays_at(camera, vv + v0, uu + u0)
            ofc = invert_pose(cfo)
            origins = np.repeat(ofc[:3, 3][None, :], len(dirs_c), axis=0)
            dirs_o = dirs_c @ ofc[:3, :3].T
            hit = _intersector(t.mesh).intersects_any(origins, dirs_o)
            full[vv[hit] + v0, uu[hit] + u0] = True
        masks[k] = full
    return masks


def _materials(layout: SceneLayout) -> tuple[str, ...]:
    return tuple(t.material for t in layout.templates)


def _check_camera(camera: Camera) -> None:
    if camera.has_distortion:
        raise InputError(
            "the renderer draws ideal pinhole images: pass a camera with zero distortion "
            "(undistort real intrinsics first, e.g. with cv2.getOptimalNewCameraMatrix)"
        )
    camera.require_world_from_camera()


def _visible_masks(ids: np.ndarray, n: int) -> BoolArray:
    return ids[None, :, :] == np.arange(1, n + 1, dtype=ids.dtype)[:, None, None]


# -- MuJoCo backend --------------------------------------------------------------------------
_GL_CONTEXT: Any = None
_GL_FAILED: str | None = None


def _gl_context(width: int, height: int) -> Any:
    """A process-wide OpenGL context (created and probed once); raises SimulationError when none works.

    The probe builds a MuJoCo render context on a one-geom model, which fails cleanly when the GL backend
    picked at `import mujoco` time (MUJOCO_GL) cannot render here.
    """
    global _GL_CONTEXT, _GL_FAILED
    if _GL_CONTEXT is not None:
        return _GL_CONTEXT
    if _GL_FAILED is not None:
        raise SimulationError(_GL_FAILED)
    try:
        mujoco = import_mujoco()
        ctx = mujoco.GLContext(max(width, 64), max(height, 64))
        ctx.make_current()
        probe = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size="0.1"/></worldbody></mujoco>')
        mujoco.MjrContext(probe, mujoco.mjtFontScale.mjFONTSCALE_100).free()
    except Exception as exc:  # any GL/EGL failure means "no OpenGL here"
        _GL_FAILED = (
            f"no OpenGL context for MuJoCo (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {exc}; on a headless machine "
            "set MUJOCO_GL=egl before anything imports mujoco"
        )
        raise SimulationError(_GL_FAILED) from exc
    _GL_CONTEXT = ctx
    return ctx


def opengl_available() -> bool:
    """Whether MuJoCo can make an offscreen OpenGL context in this process."""
    try:
        _gl_context(64, 64)
    except SimulationError:
        return False
    return True


def release_gl_context() -> None:
    """Leave the process-wide OpenGL context current on no thread, so that another thread may render next (the
    overlapped cell loop renders on its capture thread; EGL refuses a context current on another thread). EGL and
    GLFW backends; a no-op for the others and when no context was made."""
    ctx = _GL_CONTEXT
    if ctx is None:
        return
    module = type(ctx).__module__
    if module.startswith("mujoco.egl"):
        from mujoco import egl

        gl = egl.EGL
        gl.eglMakeCurrent(egl.EGL_DISPLAY, gl.EGL_NO_SURFACE, gl.EGL_NO_SURFACE, gl.EGL_NO_CONTEXT)
    elif module.startswith("mujoco.glfw"):
        from mujoco import glfw as mujoco_glfw  # mujoco's own GLFW backend (it brings the glfw binding)

        mujoco_glfw.glfw.make_context_current(None)  # type: ignore[attr-defined, unused-ignore]


class MujocoSceneRenderer:
    """Renders one layout from many cameras with MuJoCo (model and GPU buffers built once).

    multisample: MSAA samples of the offscreen buffer; 0 (default) keeps ids and depth exact per pixel and
    is about 3x faster with software OpenGL (sensor models add their own optical blur to RGB).
    """

    def __init__(self, layout: SceneLayout, width: int, height: int, multisample: int = 0) -> None:
        mujoco = import_mujoco()
        self.layout = layout
        self.width, self.height = int(width), int(height)
        self._ctx = _gl_context(self.width, self.height)
        self._ctx.make_current()
        xml = build_mjcf(
            layout.templates,
            layout.static_boxes,
            layout.world_from_object,
            free=False,
            offscreen_size=(width, height),
            offscreen_samples=multisample,
        )
        self.model = load_model(xml)
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self.scene = mujoco.MjvScene(self.model, maxgeom=max(1000, 4 * self.model.ngeom))
        self.option = mujoco.MjvOption()
        self.option.geomgroup[:] = 0
        self.option.geomgroup[0] = 1
        self.context = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)
        self.context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self.rect = mujoco.MjrRect(0, 0, self.width, self.height)
        # geom id -> part index + 1 (0 for static geometry)
        body_to_part = np.zeros(self.model.nbody, dtype=np.int32)
        for k in range(layout.n_parts):
            body_to_part[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, f"p{k}")] = k + 1
        self._geom_to_part = body_to_part[self.model.geom_bodyid]
        self._cam = mujoco.MjvCamera()
        self._cam.type = mujoco.mjtCamera.mjCAMERA_FREE

    def close(self) -> None:
        if self.context is not None:
            self._ctx.make_current()
            self.context.free()
            self.context = None

    def _set_camera(self, camera: Camera) -> tuple[float, float]:
        mujoco = import_mujoco()
        mujoco.mjv_updateScene(
            self.model, self.data, self.option, None, self._cam, mujoco.mjtCatBit.mjCAT_ALL, self.scene
        )
        wfc = camera.require_world_from_camera()
        near, far = _NEAR_M, _FAR_M
        fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
        w, h = camera.width, camera.height
        left = near * (-0.5 - cx) / fx
        right = near * (w - 0.5 - cx) / fx
        top = near * (cy + 0.5) / fy
        bottom = -near * (h - 0.5 - cy) / fy
        for i in range(2):
            gl = self.scene.camera[i]
            gl.pos[:] = wfc[:3, 3]
            gl.forward[:] = wfc[:3, 2]
            gl.up[:] = -wfc[:3, 1]
            gl.frustum_near = near
            gl.frustum_far = far
            gl.frustum_center = (left + right) / 2
            gl.frustum_width = (right - left) / 2
            gl.frustum_bottom = bottom
            gl.frustum_top = top
            gl.orthographic = 0
        return float(self.scene.camera[0].frustum_near), float(self.scene.camera[0].frustum_far)

    def render(self, camera: Camera) -> Rendering:
        """Render the layout through `camera` (needs world_from_camera and zero distortion)."""
        _check_camera(camera)
        mujoco = import_mujoco()
        if (camera.width, camera.height) != (self.width, self.height):
            raise InputError(
                f"this renderer was built for {self.width}x{self.height}, got a {camera.width}x{camera.height} camera"
            )
        self._ctx.make_current()
        near, far = self._set_camera(camera)
        h, w = self.height, self.width
        # pass 1: segmentation colours + depth
        flags = self.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 1
        flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1
        seg = np.empty((h, w, 3), dtype=np.uint8)
        zbuf = np.empty((h, w), dtype=np.float32)
        mujoco.mjr_render(self.rect, self.scene, self.context)
        mujoco.mjr_readPixels(seg, zbuf, self.rect, self.context)
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 0
        flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 0
        # pass 2: shaded colour
        rgb = np.empty((h, w, 3), dtype=np.uint8)
        mujoco.mjr_render(self.rect, self.scene, self.context)
        mujoco.mjr_readPixels(rgb, None, self.rect, self.context)
        seg, zbuf, rgb = seg[::-1], zbuf[::-1], np.ascontiguousarray(rgb[::-1])
        # reversed-Z (1 at near, 0 at far) -> metric z-depth, in float64
        b = zbuf.astype(np.float64)
        depth = far * near / ((far - near) * b + near)
        depth[b <= 0.0] = 0.0
        segid = (
            seg[..., 0].astype(np.int64) | (seg[..., 1].astype(np.int64) << 8) | (seg[..., 2].astype(np.int64) << 16)
        )
        lut = np.zeros(self.scene.ngeom + 2, dtype=np.int32)
        for g in range(self.scene.ngeom):
            sg = self.scene.geoms[g]
            if sg.objtype == mujoco.mjtObj.mjOBJ_GEOM and sg.segid >= 0:
                lut[sg.segid + 1] = self._geom_to_part[sg.objid]
        ids = lut[np.clip(segid, 0, len(lut) - 1)]
        ids[depth == 0] = 0
        vis = _visible_masks(ids, self.layout.n_parts)
        full = _full_masks(self.layout, camera, depth, ids)
        return Rendering(rgb, depth, ids, full, vis, "mujoco", _materials(self.layout))


# -- ray-cast backend ------------------------------------------------------------------------
class RaycastSceneRenderer:
    """Renders one layout by casting a ray per pixel (trimesh + embree); no OpenGL needed."""

    def __init__(self, layout: SceneLayout, width: int, height: int) -> None:
        import trimesh

        self.layout = layout
        self.width, self.height = int(width), int(height)
        meshes, owner, colors = [], [], []
        for k in range(layout.n_parts):
            m = layout.part_mesh_world(k)
            meshes.append(m)
            owner.append(np.full(len(m.faces), k + 1, dtype=np.int32))
            rgba = PART_COLORS.get(layout.templates[k].name, (0.6, 0.6, 0.6, 1.0))
            colors.append(np.tile(np.asarray(rgba[:3]), (len(m.faces), 1)))
        for name, pose, size in layout.static_boxes:
            m = trimesh.creation.box(extents=size, transform=pose)
            meshes.append(m)
            owner.append(np.zeros(len(m.faces), dtype=np.int32))
            rgb = (0.55, 0.45, 0.35) if name == "table" else ((0.2, 0.2, 0.22) if "belt" in name else (0.45, 0.5, 0.58))
            colors.append(np.tile(np.asarray(rgb), (len(m.faces), 1)))
        self.mesh: trimesh.Trimesh = trimesh.util.concatenate(meshes)  # type: ignore[assignment]
        self.face_owner = np.concatenate(owner)
        self.face_color = np.concatenate(colors)
        self.face_normals = np.asarray(self.mesh.face_normals, dtype=np.float64)
        self._inter = _intersector(self.mesh)

    def close(self) -> None:
        return None

    def render(self, camera: Camera) -> Rendering:
        """Render the layout through `camera` (needs world_from_camera and zero distortion)."""
        _check_camera(camera)
        h, w = camera.height, camera.width
        if (w, h) != (self.width, self.height):
            raise InputError(f"this renderer was built for {self.width}x{self.height}, got {w}x{h}")
        wfc = camera.require_world_from_camera()
        rays_c = _pixel_rays(camera).reshape(-1, 3)
        dirs = rays_c @ wfc[:3, :3].T
        origins = np.repeat(wfc[:3, 3][None, :], len(dirs), axis=0)
        tri, ray, loc = self._inter.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
        flat_depth = np.zeros(h * w)
        flat_ids = np.zeros(h * w, dtype=np.int32)
        rgb = np.zeros((h * w, 3))
        flat_depth[ray] = (loc - wfc[:3, 3]) @ wfc[:3, 2]
        flat_ids[ray] = self.face_owner[tri]
        unit = dirs[ray] / np.linalg.norm(dirs[ray], axis=1, keepdims=True)
        lambert = np.abs(np.einsum("ij,ij->i", self.face_normals[tri], unit))
        rgb[ray] = self.face_color[tri] * (0.35 + 0.6 * lambert)[:, None]
        depth = flat_depth.reshape(h, w)
        ids = flat_ids.reshape(h, w)
        rgb8 = np.clip(rgb.reshape(h, w, 3) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        vis = _visible_masks(ids, self.layout.n_parts)
        full = _full_masks(self.layout, camera, depth, ids)
        return Rendering(rgb8, depth, ids, full, vis, "raycast", _materials(self.layout))


SceneRenderer = MujocoSceneRenderer | RaycastSceneRenderer


def make_renderer(layout: SceneLayout, width: int, height: int, backend: str = "auto") -> SceneRenderer:
    """A renderer for `layout` at `width` x `height`: 'mujoco', 'raycast', or 'auto' (MuJoCo, else ray casting)."""
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend in ("auto", "mujoco"):
        try:
            return MujocoSceneRenderer(layout, width, height)
        except SimulationError as exc:
            if backend == "mujoco":
                raise
            logger.warning("MuJoCo rendering unavailable (%s); falling back to ray casting", exc)
    return RaycastSceneRenderer(layout, width, height)


def render(layout: SceneLayout, camera: Camera, backend: str = "auto") -> Rendering:
    """Render `layout` through `camera` (with world_from_camera). For many views build `make_renderer` once."""
    _check_camera(camera)
    renderer = make_renderer(layout, camera.width, camera.height, backend)
    try:
        return renderer.render(camera)
    finally:
        renderer.close()
