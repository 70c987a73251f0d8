"""Depth-sensor models: turn an ideal `Rendering` into what a real RGB-D camera would deliver.

Depth noise RMS follows sigma(z) = noise_floor + noise_per_m * z + z^2 * sigma_d / (fx * B) (stereo: disparity
noise sigma_d in pixels, focal fx in pixels, baseline B), part of it spatially correlated (the matching
window), then quantised. Holes: the stereo/projector visibility model (occlusion shadows beside near objects
and the D4xx invalid band at the left image edge both come from points the second view cannot see), dropouts
at depth edges and grazing angles, range limits and random speckle. RGB gets gain, white balance, an
illumination gradient, shot and read noise. Presets: ideal, d435, d455, zed2, zivid
(figures from shared/reference/sensor_noise.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from statistics import NormalDist

import numpy as np

from normpos_grasp.camera.model import Camera
from normpos_grasp.errors import InputError
from normpos_grasp.sim.render import Rendering
from normpos_grasp.typing import BoolArray, FloatArray, UInt8Array


@dataclass(frozen=True)
class SensorModel:
    """One depth camera's imperfections. Lengths in metres, image measures in pixels.

    disparity_noise_px: stereo disparity noise sigma_d (pixels); baseline_m: stereo baseline or projector
    offset along +x of the camera frame (metres), used for noise, occlusion shadows and the left band.
    noise_floor_m / noise_per_m: constant (m) and distance-proportional (m per m) RMS terms.
    correlation_px: Gaussian sigma (pixels) of the correlated part; correlated_fraction: its share of the
    noise variance (0..1). depth_unit_m: quantisation step (0 = none). depth_bias_m: systematic offset (+ far).
    min_range_m / max_range_m: valid depth range. shadows: invalidate points the second view cannot see
    (includes the left band); edge_jump_m / edge_hole_px / edge_hole_prob: depth steps above edge_jump_m
    drop pixels within edge_hole_px with this probability. grazing_deg: incidence angle beyond which pixels
    drop (90 = never), over a 10 degree ramp. dropout_prob: random speckle holes.
    rgb_read_noise_dn / rgb_shot_noise: RGB noise (digital numbers; shot scale per sqrt(DN)).
    rgb_gain: (min, max) global brightness factor; rgb_white_balance: per-channel gain jitter (sigma);
    rgb_gradient: peak relative brightness change of a random linear illumination gradient.
    rgb_blur_px: Gaussian sigma (pixels) of the lens blur applied to RGB before noise (0 = none).
    material_dropout: (material, fraction) pairs: that share of the pixels of parts made of the material
        loses its depth in blobs a few pixels wide (specular metal, dark or textureless surfaces).
    """

    name: str = "ideal"
    disparity_noise_px: float = 0.0
    baseline_m: float = 0.0
    noise_floor_m: float = 0.0
    noise_per_m: float = 0.0
    correlation_px: float = 0.0
    correlated_fraction: float = 0.0
    depth_unit_m: float = 0.0
    depth_bias_m: float = 0.0
    min_range_m: float = 0.0
    max_range_m: float = math.inf
    shadows: bool = False
    edge_jump_m: float = 0.01
    edge_hole_px: int = 0
    edge_hole_prob: float = 0.0
    grazing_deg: float = 90.0
    dropout_prob: float = 0.0
    rgb_read_noise_dn: float = 0.0
    rgb_shot_noise: float = 0.0
    rgb_gain: tuple[float, float] = (1.0, 1.0)
    rgb_white_balance: float = 0.0
    rgb_gradient: float = 0.0
    rgb_blur_px: float = 0.0
    material_dropout: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if self.disparity_noise_px > 0 and self.baseline_m <= 0:
            raise InputError(f"{self.name}: stereo noise needs baseline_m > 0, got {self.baseline_m}")
        if self.shadows and self.baseline_m <= 0:
            raise InputError(f"{self.name}: shadows need baseline_m > 0 (the second view's offset)")
        if not 0.0 <= self.correlated_fraction <= 1.0 or not 0.0 <= self.edge_hole_prob <= 1.0:
            raise InputError(f"{self.name}: correlated_fraction and edge_hole_prob must lie in [0, 1]")
        if any(not 0.0 <= p <= 1.0 for _, p in self.material_dropout):
            raise InputError(f"{self.name}: material_dropout fractions must lie in [0, 1], got {self.material_dropout}")
        if not 0.0 <= self.dropout_prob < 1.0:
            raise InputError(f"{self.name}: dropout_prob must lie in [0, 1), got {self.dropout_prob}")
        if self.min_range_m < 0 or self.max_range_m <= self.min_range_m:
            raise InputError(
                f"{self.name}: need 0 <= min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}"
            )

    # -- the formula ------------------------------------------------------------------------
    def depth_sigma_m(self, z_m: FloatArray | float, fx_px: float) -> FloatArray:
        """Depth noise RMS (metres) before quantisation at depth `z_m`, for focal length `fx_px` (pixels)."""
        z = np.asarray(z_m, dtype=np.float64)
        stereo = z * z * self.disparity_noise_px / (fx_px * self.baseline_m) if self.baseline_m > 0 else 0.0
        return np.asarray(self.noise_floor_m + self.noise_per_m * z + stereo, dtype=np.float64)

    def depth_rms_m(self, z_m: FloatArray | float, fx_px: float) -> FloatArray:
        """Expected RMS depth error (metres) including quantisation: sqrt(sigma^2 + unit^2 / 12), bias excluded."""
        s = self.depth_sigma_m(z_m, fx_px)
        return np.sqrt(s * s + self.depth_unit_m**2 / 12.0)

    # -- application ------------------------------------------------------------------------
    def apply(self, rendering: Rendering, camera: Camera, rng: np.random.Generator) -> tuple[UInt8Array, FloatArray]:
        """(rgb (H, W, 3) uint8, depth_m (H, W) float64 with 0 = no measurement) as this sensor delivers them.

        Does not modify `rendering`; all randomness comes from `rng`.
        """
        truth = rendering.depth_m
        if truth.shape != (camera.height, camera.width):
            raise InputError(f"rendering is {truth.shape}, camera is {camera.height}x{camera.width}")
        valid = truth > 0
        holes = ~valid
        if self.shadows:
            holes |= _stereo_invisible(truth, camera.fx * self.baseline_m)
        if self.edge_hole_px > 0 and self.edge_hole_prob > 0:
            edges = _depth_edges(truth, self.edge_jump_m, self.edge_hole_px)
            holes |= edges & (rng.random(truth.shape, dtype=np.float32) < self.edge_hole_prob)
        if self.grazing_deg < 90.0:
            # drop probability ramps from 0 at grazing_deg to 1 at grazing_deg + 10 (linear in the cosine)
            cos = _incidence_cos(truth, camera)
            c0 = np.float32(np.cos(np.radians(self.grazing_deg)))
            c1 = np.float32(np.cos(np.radians(min(self.grazing_deg + 10.0, 90.0))))
            p = np.clip((c0 - cos) / max(c0 - c1, np.float32(1e-6)), 0.0, 1.0)
            holes |= rng.random(truth.shape, dtype=np.float32) < p
        if self.material_dropout and rendering.part_materials:
            holes |= self._material_holes(rendering, rng)
        depth = truth.copy()
        sigma = self.depth_sigma_m(truth, camera.fx)
        if np.any(sigma > 0):
            depth = depth + sigma * self._noise_field(truth.shape, rng) + self.depth_bias_m
        elif self.depth_bias_m:
            depth = depth + self.depth_bias_m
        if self.depth_unit_m > 0:
            depth = np.round(depth / self.depth_unit_m) * self.depth_unit_m
        holes |= (depth < self.min_range_m) | (depth > self.max_range_m) | (depth <= 0)
        if self.dropout_prob > 0:
            holes |= rng.random(truth.shape, dtype=np.float32) < self.dropout_prob
        depth[holes] = 0.0
        return self._rgb(rendering.rgb, rng), depth

    def _material_holes(self, rendering: Rendering, rng: np.random.Generator) -> BoolArray:
        """Blobs (about 3 px) covering the configured share of each listed material's visible pixels."""
        import cv2

        fractions = dict(self.material_dropout)
        lost = np.zeros(len(rendering.part_materials) + 1, dtype=np.float64)
        for k, material in enumerate(rendering.part_materials):
            lost[k + 1] = fractions.get(material, 0.0)
        if not lost.any():
            return np.zeros(rendering.depth_m.shape, dtype=bool)
        blurred = cv2.GaussianBlur(_normal_samples(rendering.depth_m.shape, rng), (0, 0), 3.0)
        field = np.asarray(blurred, dtype=np.float32) / np.float32(max(float(np.std(blurred)), 1e-12))
        # threshold so that a unit-normal field exceeds it with probability p: z = Phi^-1(1 - p)
        inv = NormalDist().inv_cdf
        thresholds = np.array([inv(1.0 - p) if 0.0 < p < 1.0 else (np.inf if p <= 0.0 else -np.inf) for p in lost])
        return np.asarray(field > thresholds[rendering.instance_ids], dtype=bool)

    def _noise_field(self, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """Unit-variance noise: white plus Gaussian-correlated parts mixed by `correlated_fraction`."""
        white = _normal_samples(shape, rng).copy()
        if self.correlated_fraction <= 0 or self.correlation_px <= 0:
            return white
        import cv2

        ksize = int(2 * math.ceil(3 * self.correlation_px) + 1)
        k1 = cv2.getGaussianKernel(ksize, self.correlation_px).astype(np.float64).reshape(-1)
        gain = float(np.sum(k1**2))  # std of blurred unit white noise: sqrt((sum k^2)^2) for the separable 2-D kernel
        corr = cv2.GaussianBlur(
            _normal_samples(shape, rng), (ksize, ksize), self.correlation_px, borderType=cv2.BORDER_REFLECT
        )
        f = self.correlated_fraction
        white *= np.float32(np.sqrt(1.0 - f))
        white += np.float32(np.sqrt(f) / gain) * corr
        return white

    def _rgb(self, rgb: UInt8Array, rng: np.random.Generator) -> UInt8Array:
        if (
            self.rgb_read_noise_dn <= 0
            and self.rgb_shot_noise <= 0
            and self.rgb_gain == (1.0, 1.0)
            and self.rgb_white_balance <= 0
            and self.rgb_gradient <= 0
            and self.rgb_blur_px <= 0
        ):
            return rgb.copy()
        h, w = rgb.shape[:2]
        gain = np.float32(rng.uniform(*self.rgb_gain))
        wb = (gain * (1.0 + self.rgb_white_balance * rng.standard_normal(3))).astype(np.float32)
        phi = rng.uniform(0, 2 * np.pi)
        amp = np.float32(self.rgb_gradient * rng.random())
        u = np.linspace(-1, 1, w, dtype=np.float32)
        v = np.linspace(-1, 1, h, dtype=np.float32)
        ramp = 1.0 + amp * (np.float32(np.cos(phi)) * u[None, :] + np.float32(np.sin(phi)) * v[:, None])
        import cv2

        if self.rgb_blur_px > 0:
            rgb = np.asarray(cv2.GaussianBlur(rgb, (0, 0), self.rgb_blur_px, borderType=cv2.BORDER_REFLECT), np.uint8)
        img = rgb.astype(np.float32)
        img *= (ramp[:, :, None] * wb).astype(np.float32)  # illumination gradient x gain x white balance
        # per-channel noise sigma by look-up on the raw value (shot noise ~ sqrt of the signal)
        levels = np.arange(256, dtype=np.float32)[:, None] * wb[None, :]
        lut = np.sqrt(np.float32(self.rgb_read_noise_dn) ** 2 + np.float32(self.rgb_shot_noise) ** 2 * levels)
        sigma = cv2.LUT(np.ascontiguousarray(rgb), lut.reshape(1, 256, 3).astype(np.float32))
        sigma *= _normal_samples(img.shape, rng)
        img += sigma
        img += np.float32(0.5)
        np.clip(img, 0, 255, out=img)
        return img.astype(np.uint8)


_POOL_SIZE = 1 << 23
_POOL: list[np.ndarray] = []


def _normal_samples(shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Standard normal float32 samples of `shape`, read from a fixed pool of i.i.d. normals.

    Drawing millions of normals per frame dominates the sensor's cost on small CPUs; instead a process-wide
    pool (8 M values, fixed seed) is read at an offset and with a sign drawn from `rng`. Within one image the
    samples are i.i.d.; different frames see shifted windows of the same pool. Deterministic for `rng`.
    """
    n = int(np.prod(shape))
    if n > _POOL_SIZE // 2:
        return rng.standard_normal(shape, dtype=np.float32)
    if not _POOL:
        _POOL.append(np.random.default_rng(0x5E5A).standard_normal(_POOL_SIZE, dtype=np.float32))
    start = int(rng.integers(0, _POOL_SIZE - n))
    window = _POOL[0][start : start + n].reshape(shape)
    return window * np.float32(-1.0) if rng.random() < 0.5 else window


def _stereo_invisible(depth: FloatArray, focal_baseline: float) -> BoolArray:
    """Pixels the second view (offset +B along x) cannot see: occlusion shadows and the left band.

    A point at column u maps to u' = u - fB/z in the second view; it is hidden when it leaves that image
    (u' < -0.5) or when some pixel to its right maps at or left of it (their rays cross in front of it).
    """
    h, w = depth.shape
    valid = depth > 0
    u = np.arange(w, dtype=np.float64)[None, :]
    with np.errstate(divide="ignore"):
        up = np.where(valid, u - focal_baseline / np.where(valid, depth, 1.0), np.inf)
    # minimum of u' over pixels strictly to the right
    rev_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([rev_min[:, 1:], np.full((h, 1), np.inf)], axis=1)
    hidden = (up > right_min - 0.5) | (up < -0.5)
    return hidden & valid


def _depth_edges(depth: FloatArray, jump_m: float, radius_px: int) -> BoolArray:
    import cv2

    d = depth
    edge = np.zeros(d.shape, dtype=bool)
    dx = np.abs(np.diff(d, axis=1)) > jump_m
    dy = np.abs(np.diff(d, axis=0)) > jump_m
    edge[:, :-1] |= dx
    edge[:, 1:] |= dx
    edge[:-1, :] |= dy
    edge[1:, :] |= dy
    if radius_px > 1:
        kernel = np.ones((2 * radius_px - 1, 2 * radius_px - 1), dtype=np.uint8)
        edge = cv2.dilate(edge.astype(np.uint8), kernel).astype(bool)
    return edge


def _incidence_cos(depth: FloatArray, camera: Camera) -> np.ndarray:
    """(H, W) float32 cosine of the angle between each pixel's viewing ray and the surface normal from depth.

    With g = (fx dz/du, fy dz/dv) the normal is n = (-gx, -gy, gx x + gy y + z) for the ray r = (x, y, 1),
    so cos = n.r / (|n| |r|) = z / (|n| |r|). Pixels without depth get 1 (no grazing hole).
    """
    z = depth.astype(np.float32)
    gx = np.zeros_like(z)
    gy = np.zeros_like(z)
    np.subtract(z[:, 1:], z[:, :-1], out=gx[:, :-1])
    np.subtract(z[1:], z[:-1], out=gy[:-1])
    gx *= np.float32(camera.fx)
    gy *= np.float32(camera.fy)
    x = ((np.arange(camera.width, dtype=np.float32) - np.float32(camera.cx)) / np.float32(camera.fx))[None, :]
    y = ((np.arange(camera.height, dtype=np.float32) - np.float32(camera.cy)) / np.float32(camera.fy))[:, None]
    nz = gx * x
    nz += gy * y
    nz += z
    norm2 = gx * gx
    norm2 += gy * gy
    norm2 += nz * nz
    norm2 *= x * x + y * y + np.float32(1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = z / np.sqrt(norm2)
    cos[~(depth > 0) | ~np.isfinite(cos)] = 1.0
    return cos


_RGB_TYPICAL = {
    "rgb_read_noise_dn": 2.0,
    "rgb_shot_noise": 0.35,
    "rgb_gain": (0.85, 1.15),
    "rgb_white_balance": 0.03,
    "rgb_gradient": 0.15,
    "rgb_blur_px": 0.6,
}
# specular metal loses stereo depth in blobs; passive stereo (ZED) also on textureless plastics
_METAL_HOLES = (("aluminium", 0.08), ("steel", 0.15))

#: Sensor presets; stereo disparity noise chosen to reproduce the RMS figures of sensor_noise.md at the
#: presets' focal lengths (D435: 0.9 / 3.6 / 14 mm at 0.5 / 1 / 2 m; D455: 1.9 mm at 1 m; ZED 2: 2.8 mm at 1 m).
SENSOR_PRESETS: dict[str, SensorModel] = {
    "ideal": SensorModel(name="ideal"),
    "d435": SensorModel(
        name="d435",
        disparity_noise_px=0.11,
        baseline_m=0.050,
        correlation_px=2.0,
        correlated_fraction=0.6,
        depth_unit_m=0.001,
        min_range_m=0.2,
        max_range_m=6.0,
        shadows=True,
        edge_jump_m=0.01,
        edge_hole_px=2,
        edge_hole_prob=0.5,
        grazing_deg=78.0,
        dropout_prob=0.002,
        material_dropout=_METAL_HOLES,
        **_RGB_TYPICAL,  # type: ignore[arg-type]
    ),
    "zed2": SensorModel(
        name="zed2",
        disparity_noise_px=0.176,
        baseline_m=0.120,
        correlation_px=3.0,
        correlated_fraction=0.7,
        depth_unit_m=0.0,
        min_range_m=0.3,
        max_range_m=20.0,
        shadows=True,
        edge_jump_m=0.01,
        edge_hole_px=3,
        edge_hole_prob=0.7,
        grazing_deg=75.0,
        dropout_prob=0.005,
        material_dropout=(("aluminium", 0.12), ("steel", 0.2), ("pom", 0.08), ("abs", 0.08)),
        **_RGB_TYPICAL,  # type: ignore[arg-type]
    ),
    "zivid": SensorModel(
        name="zivid",
        baseline_m=0.135,
        noise_per_m=60e-6 / 0.7,  # about 60 um at its 0.7 m optimum, proportional to distance
        correlation_px=1.0,
        correlated_fraction=0.3,
        depth_unit_m=0.0,
        min_range_m=0.3,
        max_range_m=1.5,
        shadows=True,
        edge_jump_m=0.005,
        edge_hole_px=1,
        edge_hole_prob=0.8,
        grazing_deg=80.0,
        dropout_prob=0.0005,
        material_dropout=(("aluminium", 0.02), ("steel", 0.04)),
        rgb_read_noise_dn=1.0,
        rgb_shot_noise=0.2,
        rgb_gain=(0.95, 1.05),
        rgb_white_balance=0.01,
        rgb_gradient=0.05,
        rgb_blur_px=0.5,
    ),
}
# The D455 is the D435's matcher with a wider baseline and a longer range (same holes and RGB).
SENSOR_PRESETS["d455"] = replace(
    SENSOR_PRESETS["d435"], name="d455", disparity_noise_px=0.0704, baseline_m=0.095, min_range_m=0.4, max_range_m=10.0
)


def sensor_preset(name: str, **overrides: object) -> SensorModel:
    """The preset `name` (ideal, d435, d455, zed2, zivid), with fields replaced by `overrides`."""
    if name not in SENSOR_PRESETS:
        raise InputError(f"unknown sensor preset {name!r}; choose one of {sorted(SENSOR_PRESETS)}")
    preset = SENSOR_PRESETS[name]
    return replace(preset, **overrides) if overrides else preset  # type: ignore[arg-type]
