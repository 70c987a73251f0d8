"""The depth the camera should see while the arm moves.

The reference is the depth frame of the last measurement (the one the plan was made from), reduced by `downsample`
(mean of the valid pixels of each block). Where that frame saw the arm (its silhouette at the joints it was taken
at) or saw nothing, the reference falls back to the cell's static boxes (and floor) rendered through the camera.
Each pixel's threshold is `k_sigma` times the depth noise of the difference of two frames (sqrt(2) sigma(z) of the
sensor model), taken at the nearest reference depth of its 3x3 neighbourhood, so a depth edge that jitters by a
pixel never reads as something new. The arm, tool and held part are the link capsules of the robot model, the
tool's boxes as bounding capsules and a sphere at the TCP, each grown by `silhouette_pad_m` (latency and tracking
error); a pixel is the arm when its back-projected point lies inside one of them at some pose the arm took while the
frame was on its way (`arm_explains`, a 3D test). Their silhouette (`silhouette_depth`: each capsule cut into
pieces drawn as wide as they look at their own nearest depth) marks the pixels the arm hid in the reference.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.cell.config import BoxSpec
from normpos_grasp.errors import InputError
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.records.tool import ToolModel
from normpos_grasp.typing import BoolArray, FloatArray
from normpos_grasp.watch.zones import ArmSegments, slab_interval

SigmaFn = Callable[[FloatArray], FloatArray]  # depth noise RMS (m) of one frame at depth z (m)
# Pixels the arm hid in the reference: anything nearer than the static scene by more than this is new even before
# the pixel is learned (parts in a bin rest lower than this), m.
UNKNOWN_HEIGHT_M = 0.2


def downsample_depth(depth_m: FloatArray, factor: int) -> np.ndarray:
    """(H // f, W // f) float32 mean of the valid (> 0) pixels of each f x f block; 0 where under half are valid."""
    d = np.asarray(depth_m, dtype=np.float32)
    if d.ndim != 2:
        raise InputError(f"depth must be (H, W), got {d.shape}")
    if factor == 1:
        return np.where(np.isfinite(d) & (d > 0), d, np.float32(0.0))
    h, w = d.shape[0] // factor, d.shape[1] // factor
    blocks = d[: h * factor, : w * factor].reshape(h, factor, w, factor)
    blocks = np.where(np.isfinite(blocks) & (blocks > 0), blocks, np.float32(0.0))
    total = blocks.sum(axis=(1, 3), dtype=np.float32)
    count = np.count_nonzero(blocks, axis=(1, 3))
    need = (factor * factor + 1) // 2
    return np.where(count >= need, total / np.maximum(count, 1), np.float32(0.0)).astype(np.float32)


def watch_camera(camera: Camera, factor: int) -> Camera:
    """The camera of the reduced image (intrinsics scaled by 1 / factor, same extrinsics)."""
    cam = camera if factor == 1 else camera.scaled(1.0 / factor)
    want = (camera.width // factor, camera.height // factor)
    if (cam.width, cam.height) != want:
        cam = Camera(cam.K, want[0], want[1], cam.distortion, cam.depth_scale_m, cam.world_from_camera)
    return cam


class ArmCapsules:
    """The arm's link capsules (robot model), the tool's boxes as bounding capsules and the flange-to-TCP body, each
    fixed to a DH frame (0 = base .. 6 = flange); `at` places them for a batch of joint vectors at once."""

    def __init__(self, arm: ArmModel, tool: ToolModel | None = None) -> None:
        self.arm = arm
        joints, starts, ends, radii = [], [], [], []

        def add(joint: int, pose: FloatArray, kind: str, size: tuple[float, ...]) -> None:
            if kind == "box":
                half = np.asarray(size, dtype=np.float64) / 2
                k = int(np.argmax(half))
                axis = pose[:3, k] * half[k]
                r = float(np.linalg.norm(np.delete(half, k)))
            elif kind == "sphere":
                axis, r = np.zeros(3), float(size[0])
            else:
                axis, r = pose[:3, 2] * (float(size[1]) / 2 if len(size) > 1 else 0.0), float(size[0])
            joints.append(joint)
            starts.append(pose[:3, 3] - axis)
            ends.append(pose[:3, 3] + axis)
            radii.append(r)

        for shape in arm.shapes:
            add(shape.joint, np.asarray(shape.link_from_shape, dtype=np.float64), shape.kind, shape.size)
        self.flange_from_tcp = np.eye(4) if tool is None else np.asarray(tool.flange_from_tcp, dtype=np.float64)
        if tool is not None:
            for tool_shape, tcp_from_shape in tool.posed_shapes(tool.stroke_m):
                add(6, self.flange_from_tcp @ tcp_from_shape, tool_shape.kind, tool_shape.size)
            # the flange-to-TCP body, in case the tool's boxes leave gaps
            body = np.eye(4)
            body[:3, 3] = self.flange_from_tcp[:3, 3] / 2
            body[:3, 2] = self.flange_from_tcp[:3, 3] / max(float(np.linalg.norm(self.flange_from_tcp[:3, 3])), 1e-9)
            add(6, body, "capsule", (0.04, float(np.linalg.norm(self.flange_from_tcp[:3, 3]))))
        self.joints = np.array(joints, dtype=np.int64)
        self.start = np.array(starts)
        self.end = np.array(ends)
        self.radius = np.array(radii)

    def at(self, q: FloatArray, held_radius_m: float = 0.0, pad_m: float = 0.0) -> ArmSegments:
        """Capsules (world frame) at joints (6,) or along a path (M, 6), grown by `pad_m`; with a sphere of
        `held_radius_m` at the TCP for a held part."""
        qs = np.asarray(q, dtype=np.float64).reshape(-1, 6)
        frames = self.arm.frames(qs)  # (M, 7, 4, 4)
        fj = frames[:, self.joints]  # (M, C, 4, 4)
        rot = fj[..., :3, :3]
        off = fj[..., :3, 3]
        a = np.einsum("mcij,cj->mci", rot, self.start) + off
        b = np.einsum("mcij,cj->mci", rot, self.end) + off
        r = np.broadcast_to(self.radius, a.shape[:2])
        if held_radius_m > 0:
            tcp = (frames[:, 6] @ self.flange_from_tcp)[:, :3, 3]
            a = np.concatenate([a, tcp[:, None]], axis=1)
            b = np.concatenate([b, tcp[:, None]], axis=1)
            r = np.concatenate([r, np.full((len(qs), 1), held_radius_m)], axis=1)
        # link by link (each link's poses along the path together: `ArmSegments.within` culls them as a group)
        a, b, r = a.transpose(1, 0, 2), b.transpose(1, 0, 2), np.asarray(r).T
        return ArmSegments(a.reshape(-1, 3), b.reshape(-1, 3), r.reshape(-1) + pad_m)


def arm_segments(
    arm: ArmModel, q: FloatArray, tool: ToolModel | None = None, held_radius_m: float = 0.0, pad_m: float = 0.0
) -> ArmSegments:
    """The arm's link capsules at joints `q` (6,) or (M, 6) rad, the tool's boxes as bounding capsules and a sphere
    of `held_radius_m` at the TCP for a held part, all grown by `pad_m`; world frame."""
    return ArmCapsules(arm, tool).at(q, held_radius_m, pad_m)


def silhouette_depth(camera: Camera, segments: ArmSegments) -> tuple[np.ndarray, np.ndarray]:
    """(near, far) (H, W) float32: the depth range the capsules may occupy at each pixel (inf / -inf where none
    covers it). Each capsule is cut along its axis into pieces whose depth changes by at most its radius; each piece
    is drawn as a thick line with round caps between its projected ends, as wide as it looks at its own nearest
    depth, and spans its own nearest to farthest depth (conservative, and tight where a link slants towards the
    camera: a whole-capsule width and span would hide a hand beside or under the far end of a slanted link)."""
    import cv2

    h, w = camera.height, camera.width
    near = np.full((h, w), np.inf, dtype=np.float32)
    far = np.full((h, w), -np.inf, dtype=np.float32)
    if len(segments.radius) == 0:
        return near, far
    cfw = camera.camera_from_world
    a = segments.start @ cfw[:3, :3].T + cfw[:3, 3]
    b = segments.end @ cfw[:3, :3].T + cfw[:3, 3]
    r = segments.radius
    z_near = np.minimum(a[:, 2], b[:, 2]) - r
    z_far = np.maximum(a[:, 2], b[:, 2]) + r
    reaches = z_near < 0.05
    if np.any(reaches & (z_far > 0.05)):
        # a capsule reaches the camera: whatever it may cover is unknown, so it covers the whole view
        near[:] = 0.0
        far[:] = np.inf
        return near, far
    keep = np.nonzero(~reaches)[0]
    a, b, r = a[keep], b[keep], r[keep]
    pieces = np.clip(np.ceil(np.abs(b[:, 2] - a[:, 2]) / np.maximum(r, 0.01)), 1, 16).astype(np.int64)
    idx = np.repeat(np.arange(len(r)), pieces)
    first = np.repeat(np.cumsum(pieces) - pieces, pieces)
    k = np.arange(len(idx)) - first
    s0 = (k / pieces[idx])[:, None]
    s1 = ((k + 1) / pieces[idx])[:, None]
    pa = a[idx] + s0 * (b[idx] - a[idx])
    pb = a[idx] + s1 * (b[idx] - a[idx])
    pr = r[idx]
    zn = np.minimum(pa[:, 2], pb[:, 2]) - pr
    zf = np.maximum(pa[:, 2], pb[:, 2]) + pr
    ua = np.round(np.clip(camera.project(pa), -1e4, 1e4)).astype(np.int64)
    ub = np.round(np.clip(camera.project(pb), -1e4, 1e4)).astype(np.int64)
    width = np.minimum(2 * np.ceil(camera.fx * pr / zn) + 2, 4000).astype(np.int64)
    # painter's order: farthest near-depth first, so each pixel ends with the least near depth covering it (and the
    # greatest far depth, drawn in increasing order)
    for order, image, values in ((np.argsort(-zn), near, zn), (np.argsort(zf), far, zf)):
        for n in order:
            cv2.line(
                image, (int(ua[n, 0]), int(ua[n, 1])), (int(ub[n, 0]), int(ub[n, 1])), float(values[n]), int(width[n])
            )
    return near, far


def silhouette(camera: Camera, segments: ArmSegments) -> BoolArray:
    """(H, W) bool: pixels the capsules may cover (see `silhouette_depth`)."""
    near, _ = silhouette_depth(camera, segments)
    return np.asarray(np.isfinite(near) | (near == 0.0))


def render_boxes(
    camera: Camera, boxes: Sequence[tuple[FloatArray, FloatArray]], floor_z: float | None = None
) -> np.ndarray:
    """(H, W) float32 z-depth of boxes (world_from_box (4, 4), full size (3,)) and an optional floor plane z =
    `floor_z`, through `camera` (no distortion); 0 where nothing is hit. Vectorised slab test per box."""
    xy = _rays(camera)
    h, w = camera.height, camera.width
    dirs = np.concatenate([xy, np.ones((h, w, 1), dtype=np.float64)], axis=2).reshape(-1, 3)
    wfc = camera.require_world_from_camera()
    best = np.full(len(dirs), np.inf)
    for world_from_box, size in boxes:
        box_from_camera = np.linalg.inv(np.asarray(world_from_box, dtype=np.float64)) @ wfc
        o = box_from_camera[:3, 3]
        d = dirs @ box_from_camera[:3, :3].T
        half = np.asarray(size, dtype=np.float64) / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half[None] - o[None]) / d
            t2 = (half[None] - o[None]) / d
        t_near, t_far = slab_interval(t1, t2)
        hit = (t_far >= np.maximum(t_near, 0.0)) & (t_near > 0)
        best = np.where(hit & (t_near < best), t_near, best)
    if floor_z is not None:
        dw = dirs @ wfc[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (floor_z - wfc[2, 3]) / dw[:, 2]
        ok = np.isfinite(t) & (t > 0)
        best = np.where(ok & (t < best), t, best)
    out = np.where(np.isfinite(best), best, 0.0).reshape(h, w)
    return out.astype(np.float32)


_RAY_CACHE: dict[tuple[bytes, int, int], FloatArray] = {}


def _rays(camera: Camera) -> FloatArray:
    """(H, W, 2) normalised pixel-centre coordinates, cached per intrinsics."""
    key = (camera.K.tobytes() + camera.distortion.tobytes(), camera.width, camera.height)
    rays = _RAY_CACHE.get(key)
    if rays is None:
        rays = camera.pixel_grid_rays()
        if len(_RAY_CACHE) > 16:
            _RAY_CACHE.clear()
        _RAY_CACHE[key] = rays
    return rays


class ExpectedScene:
    """Reference depth and per-pixel thresholds for one watch period (from one measured frame).

    camera: the stream's camera (native size, with world_from_camera); reference_depth_m: (H, W) the measured depth
    the plan was made from; sigma: depth noise RMS of one frame at depth z (m -> m, e.g. the sensor model's
    `depth_rms_m` at the native focal length); q_capture: (6,) joints when the reference was taken (None: the arm
    was not in view); static: the cell's boxes and floor height for pixels the reference cannot give.
    """

    def __init__(
        self,
        camera: Camera,
        reference_depth_m: FloatArray,
        sigma: SigmaFn,
        arm: ArmModel,
        tool: ToolModel | None,
        *,
        downsample: int = 2,
        k_sigma: float = 5.0,
        pad_m: float = 0.06,
        q_capture: FloatArray | None = None,
        static_boxes: Sequence[BoxSpec] = (),
        floor_z: float | None = None,
    ) -> None:
        import cv2

        ref_native = np.asarray(reference_depth_m)
        if ref_native.shape != (camera.height, camera.width):
            raise InputError(f"reference depth is {ref_native.shape}, camera is {camera.height}x{camera.width}")
        self.factor = int(downsample)
        self.camera = watch_camera(camera, self.factor)
        self.arm, self.tool, self.pad_m = arm, tool, float(pad_m)
        self.capsules = ArmCapsules(arm, tool)
        ref = downsample_depth(ref_native, self.factor)
        static = render_boxes(self.camera, [(b.world_from_box, b.size) for b in static_boxes], floor_z)
        ref = np.where(ref > 0, ref, static)
        self.sigma = sigma
        self.k_sigma = float(k_sigma)
        # pixels the arm hid when the reference was taken: learned from the first frame that shows them uncovered
        self.unknown = np.zeros(ref.shape, dtype=bool)
        if q_capture is not None:
            near, far = silhouette_depth(self.camera, self.capsules.at(q_capture, 0.0, self.pad_m))
            self.unknown = (ref >= near - 0.01) & (ref <= far + 0.01)
            ref = np.where(self.unknown, np.float32(0.0), ref)
        known = ref > 0
        nearest = cv2.erode(np.where(known, ref, np.float32(1e3)).astype(np.float32), np.ones((3, 3), np.uint8))
        nearest = np.where(known, np.minimum(nearest, ref), 0.0).astype(np.float32)
        self.reference = ref.astype(np.float32)
        self.limit = np.where(known, nearest - self._threshold(nearest), np.float32(0.0)).astype(np.float32)
        # until learned, an unknown pixel still flags anything more than UNKNOWN_HEIGHT_M nearer than the static scene
        guess = np.where(static > 0, static - np.float32(UNKNOWN_HEIGHT_M), np.float32(0.0)).astype(np.float32)
        self.limit = np.where(self.unknown, guess, self.limit).astype(np.float32)
        self.rays = _rays(self.camera).astype(np.float32)

    def _threshold(self, z: np.ndarray) -> np.ndarray:
        """k_sigma x the noise of the difference of two frames at depth z, m (float32)."""
        return np.float32(self.k_sigma * np.sqrt(2.0)) * np.asarray(self.sigma(z.astype(np.float64)), np.float32)

    def learn(self, depth: np.ndarray, covered: BoolArray) -> BoolArray:
        """Adopt `depth` (reduced frame) where the reference is still unknown, the pixel is not the arm (`covered`:
        `arm_explains`) and the depth is no nearer than the static scene allows (its limit); returns
        the pixels adopted (not nearer than their limit, so no candidates in this frame)."""
        if not self.unknown.any():
            return np.zeros(depth.shape, dtype=bool)
        take = self.unknown & ~covered & (depth > 0) & (depth >= self.limit)
        if take.any():
            z = depth[take]
            self.reference[take] = z
            self.limit[take] = z - self._threshold(z) - np.float32(0.01)  # no neighbourhood yet: 1 cm for edges
            self.unknown[take] = False
        return take

    def predicted_silhouette(self, q: FloatArray, held_radius_m: float = 0.0) -> BoolArray:
        """(h, w) bool: where the arm, tool and held part may appear at commanded joints `q` (6,) or along a joint
        path (M, 6) (every pose the arm took while the frame was on its way), padded."""
        return silhouette(self.camera, self.segments(q, held_radius_m, self.pad_m))

    def arm_explains(
        self, depth: np.ndarray, q: FloatArray, held_radius_m: float = 0.0, among: BoolArray | None = None
    ) -> BoolArray:
        """(h, w) bool: pixels of a reduced frame (depth, m) whose back-projected point lies inside a padded capsule
        of the arm, tool or held part at `q` (6,) or along a path (M, 6) (newest pose last), widened by the depth
        noise. Tested: the valid pixels in `among` (None: all) and the valid pixels still unknown (`learn` needs
        them). A 3D test, not an image one: a hand beside or under a link that merely overlaps its image is not
        the arm; and no drawing, so the watch thread gives up the GIL rarely (each drawing call hands it over)."""
        valid = depth > 0
        test = valid if among is None else (among & valid) | (self.unknown & valid)
        explained = np.zeros(depth.shape, dtype=bool)
        # pixels on even rows and columns first; a tested pixel of the same 2x2 block explained as the arm, at a
        # depth within the noise threshold, explains the other three (their points lie within ~1.5 px of it: 5 mm
        # at 0.6 m, against a 6 cm pad); the rest are tested themselves (an intruder's pixels all are)
        anchor = np.zeros(depth.shape, dtype=bool)
        anchor[::2, ::2] = True
        qs = np.reshape(q, (-1, 6))
        newest = self.segments(qs[-1], held_radius_m, self.pad_m)
        path = self.segments(qs, held_radius_m, self.pad_m) if len(qs) > 1 else None
        self._explain(explained, depth, np.nonzero(test & anchor), newest, path)
        v, u = np.nonzero(test & ~anchor)
        if len(v) == 0:
            return explained
        va, ua = v & ~1, u & ~1
        z = depth[v, u]
        inherit = explained[va, ua] & (np.abs(z - depth[va, ua]) <= self._threshold(z))
        explained[v[inherit], u[inherit]] = True
        self._explain(explained, depth, (v[~inherit], u[~inherit]), newest, path)
        return explained

    def _explain(
        self,
        explained: BoolArray,
        depth: np.ndarray,
        pixels: tuple[np.ndarray, ...],
        newest: ArmSegments,
        path: ArmSegments | None,
    ) -> None:
        """Mark in `explained` the pixels (rows, columns) whose point lies inside a padded capsule: the newest
        pose's first (it explains nearly all of the arm's own pixels), the whole path's for the rest."""
        v, u = pixels[0], pixels[1]
        z = depth[v, u]
        pts, margin = self.world_points(v, u, z), self._threshold(z)
        ok = newest.within(pts, margin)
        rest = np.nonzero(~ok)[0]
        if len(rest) and path is not None:
            ok[rest] = path.within(pts[rest], margin[rest])
        explained[v[ok], u[ok]] = True

    def world_points(self, v: np.ndarray, u: np.ndarray, z: np.ndarray) -> FloatArray:
        """(N, 3) world points of reduced-frame pixels (rows v, columns u) at z-depths z (m)."""
        zz = np.asarray(z, dtype=np.float64)
        cam = np.column_stack([self.rays[v, u].astype(np.float64) * zz[:, None], zz])
        wfc = self.camera.require_world_from_camera()
        return np.asarray(cam @ wfc[:3, :3].T + wfc[:3, 3])

    def segments(self, q: FloatArray, held_radius_m: float = 0.0, pad_m: float = 0.0) -> ArmSegments:
        """Capsules of the arm at joints (6,) or along a path (M, 6), world frame."""
        return self.capsules.at(q, held_radius_m, pad_m)


def joint_path(history: Sequence[tuple[float, FloatArray]], since: float, max_step_rad: float = 0.05) -> FloatArray:
    """(M, 6) joints of the (t, q) samples at or after `since` (and the last one before it), with samples added
    between neighbours so that no joint moves more than `max_step_rad` from one to the next."""
    if not history:
        raise InputError("no joint samples to draw the arm from")
    start = 0
    for i, (t, _) in enumerate(history):
        if t < since:
            start = i
    qs = [np.asarray(q, dtype=np.float64) for _, q in history[start:]]
    out = [qs[0]]
    for a, b in zip(qs[:-1], qs[1:], strict=True):
        n = int(np.ceil(float(np.max(np.abs(b - a))) / max_step_rad))
        for k in range(1, n + 1):
            out.append(a + (b - a) * (k / n))
    return np.array(out)
