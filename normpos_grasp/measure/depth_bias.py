"""Per-frame depth bias from the visible support plane (table top, bin floor) and a sanity check of the frame.

A depth sensor can read a few millimetres too far or too near over the whole image (the LM-O Kinect frame reads
about 7.4 mm behind its ground truth). Where the support plane is known in the camera frame (the cell's bin floor
or table top through the extrinsics), the bias is the robust mean of measured minus expected depth over the pixels
that see the plane:

1. every `stride`-th valid pixel: expected z-depth of the known plane along its ray, residual = measured - expected;
2. candidates: pixels with |residual| < `search_m` (the plane and flat things on it; parts standing on the plane
   read nearer by their height);
3. RANSAC plane on the candidates' points (the dominant surface near the expected plane), least-squares refined;
4. bias = median residual over the plane's inliers; spread = 1.4826 MAD.

The frame looks wrong (warnings, `DepthBiasEstimate.ok` False) when too few pixels are valid, too few see the
plane, the bias exceeds `max_bias_m`, or the measured plane is tilted from the expected one. The estimator never
uses ground truth; `correct_depth` applies the bias (z-depth, positive = the sensor reads too far).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import InputError
from normpos_grasp.measure.measure import pixel_rays
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DepthBiasOptions:
    """Settings of `estimate_depth_bias`.

    Attributes:
        stride: use every stride-th pixel in both directions.
        search_m: pixels within this distance (metres, along z) of the expected plane are candidates.
        inlier_m: RANSAC inlier distance to the measured plane, metres (plus noise_per_m2 * z^2).
        noise_per_m2: depth noise RMS per squared range, 1/m (D435: 0.0036), added to the inlier distance.
        ransac_iterations: plane hypotheses; seed: their RNG seed (private generator).
        min_valid_share: fewer valid depth pixels (share of the image) -> "too few valid pixels".
        min_plane_pixels: fewer full-resolution plane pixels -> no estimate.
        max_bias_m: a larger |bias| (metres) makes the frame look wrong (warned; not corrected by `corrected`).
        max_tilt_deg: a measured plane tilted more than this from the expected one is warned about (degrees).
        min_correct_m: `check_frame_depth` leaves the depth as it is when |bias| is below this (metres: within the
            estimate's own uncertainty, so an unbiased frame stays bit-identical).
    """

    stride: int = 4
    search_m: float = 0.06
    inlier_m: float = 0.003
    noise_per_m2: float = 0.0036
    ransac_iterations: int = 200
    seed: int = 0
    min_valid_share: float = 0.3
    min_plane_pixels: int = 2000
    max_bias_m: float = 0.03
    max_tilt_deg: float = 3.0
    min_correct_m: float = 0.002

    def __post_init__(self) -> None:
        if not (1 <= self.stride <= 32 and self.search_m > 0 and self.inlier_m > 0 and self.ransac_iterations >= 1):
            raise InputError(
                "depth bias needs stride in 1..32, search_m > 0, inlier_m > 0 and ransac_iterations >= 1; got "
                f"{self.stride}, {self.search_m}, {self.inlier_m}, {self.ransac_iterations}"
            )


@dataclass(frozen=True, eq=False)
class DepthBiasEstimate:
    """Result of `estimate_depth_bias`.

    bias_m: measured minus expected z-depth on the support plane, metres (positive: reads too far; nan: none);
    spread_m: 1.4826 MAD of the plane residuals, metres; n_plane: full-resolution pixels on the plane (estimated
    from the strided count); valid_share: share of pixels with depth; tilt_deg: angle between the measured and the
    expected plane normal; warnings: why the frame looks wrong ('' none).
    """

    bias_m: float
    spread_m: float
    n_plane: int
    valid_share: float
    tilt_deg: float
    warnings: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        """A finite bias and nothing wrong with the frame."""
        return bool(np.isfinite(self.bias_m)) and not self.warnings

    @property
    def corrected(self) -> float:
        """The bias to remove from the depth: bias_m when finite and within limits (warnings about the valid
        share or tilt do not void it), else 0."""
        return float(self.bias_m) if np.isfinite(self.bias_m) and not any("bias" in w for w in self.warnings) else 0.0


def plane_in_camera(plane_world: FloatArray, world_from_camera: FloatArray) -> FloatArray:
    """(4,) plane n . x + d = 0 (unit n) given in the world, expressed in the camera frame."""
    p = np.asarray(plane_world, dtype=np.float64).reshape(4)
    n = p[:3] / max(float(np.linalg.norm(p[:3])), 1e-12)
    d = p[3] / max(float(np.linalg.norm(p[:3])), 1e-12)
    r, t = world_from_camera[:3, :3], world_from_camera[:3, 3]
    # n . (R x_c + t) + d = 0  ->  (R^T n) . x_c + (n . t + d) = 0
    return np.concatenate([r.T @ n, [float(n @ t + d)]])


def support_plane_world(cell: CellConfig) -> FloatArray | None:
    """(4,) world plane of the surface parts rest on: the bin's inner floor, else the table top; None without."""
    if cell.bin is not None:
        pose = np.asarray(cell.bin.world_from_bin, dtype=np.float64)
        n = pose[:3, 2]
        return np.concatenate([n, [-float(n @ pose[:3, 3])]])
    for box in cell.static_boxes:
        if box.name == "table":
            pose = np.asarray(box.world_from_box, dtype=np.float64)
            n = pose[:3, 2]
            top = pose[:3, 3] + n * float(box.size[2]) / 2
            return np.concatenate([n, [-float(n @ top)]])
    return None


def estimate_depth_bias(
    camera: Camera,
    depth_m: FloatArray,
    plane_camera: FloatArray,
    options: DepthBiasOptions | None = None,
    region: Any = None,
) -> DepthBiasEstimate:
    """Depth bias of one frame from the known support plane `plane_camera` ((4,), n . x + d = 0, camera frame).

    depth_m: (H, W) z-depth, metres (0 = no reading); region: (H, W) bool, only these pixels may be plane pixels
    (None: all). See the module docstring for the method.
    """
    opts = options or DepthBiasOptions()
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.shape != (camera.height, camera.width):
        raise InputError(f"depth must be ({camera.height}, {camera.width}), got {depth.shape}")
    plane = np.asarray(plane_camera, dtype=np.float64).reshape(4)
    norm = float(np.linalg.norm(plane[:3]))
    if not norm > 0:
        raise InputError("the support plane needs a non-zero normal")
    n_exp, d_exp = plane[:3] / norm, plane[3] / norm
    valid_full = np.isfinite(depth) & (depth > 0)
    valid_share = float(valid_full.mean())
    warnings: list[str] = []
    if valid_share < opts.min_valid_share:
        warnings.append(f"too few valid depth pixels: {100 * valid_share:.0f} % (< {100 * opts.min_valid_share:.0f} %)")
    s = opts.stride
    z = depth[::s, ::s]
    rays = pixel_rays(camera)[::s, ::s]
    ok = np.isfinite(z) & (z > 0)
    if region is not None:
        ok &= np.asarray(region, dtype=bool)[::s, ::s]
    xy = rays[ok]
    zm = z[ok]
    denom = xy @ n_exp[:2] + n_exp[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z_exp = -d_exp / denom
    res = zm - z_exp
    cand = np.isfinite(res) & (z_exp > 0) & (np.abs(res) < opts.search_m)
    area = s * s
    if cand.sum() * area < opts.min_plane_pixels:
        warnings.append(f"the support plane is hardly visible: {int(cand.sum()) * area} pixels near it")
        return DepthBiasEstimate(
            float("nan"), float("nan"), int(cand.sum()) * area, valid_share, float("nan"), tuple(warnings)
        )
    pts = np.column_stack([xy[cand] * zm[cand, None], zm[cand]])
    rc = res[cand]
    tol = opts.inlier_m + opts.noise_per_m2 * pts[:, 2] ** 2
    rng = np.random.default_rng(opts.seed)
    # the dominant plane near the expected one, then a second parallel one among the rest (the table around a bin,
    # a belt beside it): of the two, the one nearer its expected place is the support plane
    best_in = _ransac_plane(pts, tol, n_exp, opts.ransac_iterations, rng)
    rest = ~best_in
    if rest.sum() * area >= opts.min_plane_pixels:
        second = np.zeros(len(pts), dtype=bool)
        second[rest] = _ransac_plane(pts[rest], tol[rest], n_exp, opts.ransac_iterations, rng)
        if second.sum() * area >= opts.min_plane_pixels and abs(float(np.median(rc[second]))) < abs(
            float(np.median(rc[best_in]))
        ):
            best_in = second
    best_n = int(best_in.sum())
    if best_n * area < opts.min_plane_pixels:
        warnings.append(f"no plane near the expected support plane: {best_n * area} pixels")
        return DepthBiasEstimate(float("nan"), float("nan"), best_n * area, valid_share, float("nan"), tuple(warnings))
    c = pts[best_in].mean(axis=0)
    _, _, vt = np.linalg.svd(pts[best_in] - c, full_matrices=False)
    nrm = vt[2] if float(vt[2] @ n_exp) >= 0 else -vt[2]
    tilt = float(np.degrees(np.arccos(np.clip(abs(float(nrm @ n_exp)), -1.0, 1.0))))
    inl = best_in & (np.abs((pts - c) @ nrm) < tol)
    r_in = rc[inl]
    bias = float(np.median(r_in))
    spread = float(1.4826 * np.median(np.abs(r_in - bias)))
    if abs(bias) > opts.max_bias_m:
        warnings.append(
            f"depth bias {bias * 1000:+.1f} mm exceeds {opts.max_bias_m * 1000:.0f} mm: check the sensor "
            "and the extrinsics"
        )
    if tilt > opts.max_tilt_deg:
        warnings.append(
            f"the measured support plane is tilted {tilt:.1f} deg from the expected one: check the extrinsics"
        )
    for w in warnings:
        logger.warning("depth frame: %s", w)
    return DepthBiasEstimate(bias, spread, int(inl.sum()) * area, valid_share, tilt, tuple(warnings))


def _ransac_plane(
    pts: FloatArray, tol: FloatArray, n_exp: FloatArray, iterations: int, rng: np.random.Generator
) -> np.ndarray:
    """(N,) inliers of the plane (normal within 20 deg of n_exp) with the most points within tol (N,) of it."""
    best_n, best_in = -1, np.zeros(len(pts), dtype=bool)
    if len(pts) < 3:
        return best_in
    for _ in range(iterations):
        tri = pts[rng.choice(len(pts), 3, replace=False)]
        nrm = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        ln = float(np.linalg.norm(nrm))
        if ln < 1e-12:
            continue
        nrm /= ln
        if abs(float(nrm @ n_exp)) < np.cos(np.deg2rad(20.0)):  # the support plane, not a wall or a part face
            continue
        inl = np.abs((pts - tri[0]) @ nrm) < tol
        k = int(inl.sum())
        if k > best_n:
            best_n, best_in = k, inl
    return best_in


def correct_depth(depth_m: FloatArray, bias_m: float) -> FloatArray:
    """(H, W) depth with `bias_m` (metres, positive = reads too far) removed from every valid pixel (0 stays 0)."""
    d = np.asarray(depth_m, dtype=np.float64)
    if not bias_m:
        return d
    return np.where(np.isfinite(d) & (d > 0), np.maximum(d - bias_m, 0.0), d)


def _over_bin_floors(camera: Camera, depth_m: FloatArray, world_from_camera: FloatArray, cell: CellConfig) -> Any:
    """(H, W) bool: the pixel's point lies over one of the cell's bin floors (walls excluded), from 5 cm below the
    floor up to the rim."""
    d = np.asarray(depth_m, dtype=np.float64)
    cam = np.column_stack([(pixel_rays(camera) * d[..., None]).reshape(-1, 2), d.reshape(-1)])
    world = cam @ world_from_camera[:3, :3].T + world_from_camera[:3, 3]
    inside = np.zeros(len(world), dtype=bool)
    for b in cell.bins:
        inv = np.linalg.inv(np.asarray(b.world_from_bin, dtype=np.float64))
        local = world @ inv[:3, :3].T + inv[:3, 3]
        lx, ly, h = (float(v) for v in b.inner_size)
        inside |= (
            (np.abs(local[:, 0]) <= lx / 2)
            & (np.abs(local[:, 1]) <= ly / 2)
            & (local[:, 2] >= -0.05)
            & (local[:, 2] <= h)
        )
    return inside.reshape(d.shape)


def check_frame_depth(
    frame: RGBDFrame, cell: CellConfig, options: DepthBiasOptions | None = None
) -> tuple[RGBDFrame, DepthBiasEstimate | None]:
    """The frame with its depth bias removed (`estimate_depth_bias` on the cell's support plane) and the estimate.

    Unchanged frame and None without extrinsics or a support plane (bin or table) in the cell; unchanged frame when
    the bias is below `min_correct_m` or not trustworthy (`DepthBiasEstimate.corrected` is 0). Warnings are logged.
    """
    opts = options or DepthBiasOptions()
    wfc = frame.camera.world_from_camera
    plane_world = support_plane_world(cell)
    if wfc is None or plane_world is None:
        return frame, None
    region = None
    if len(cell.bins) > 1:  # several bins: only pixels over a bin's floor (the table between them is another plane)
        region = _over_bin_floors(frame.camera, frame.depth_m, wfc, cell)
    est = estimate_depth_bias(frame.camera, frame.depth_m, plane_in_camera(plane_world, wfc), opts, region)
    bias = est.corrected
    if abs(bias) < opts.min_correct_m:
        return frame, est
    logger.info("depth bias %+.1f mm removed (support plane, %d pixels)", bias * 1000, est.n_plane)
    fixed = correct_depth(frame.depth_m, bias).astype(np.asarray(frame.depth_m).dtype, copy=False)
    return replace(frame, depth_m=fixed), est
