"""BOP dataset reader and writer (https://bop.felk.cvut.cz/ format): splits, scenes, frames, GT, masks, models.

Units: BOP files hold millimetres (poses, model vertices, models_info) and raw uint16 depth scaled by
`depth_scale` (mm per unit). Everything this module returns is in metres; conversion happens here only.

Layout of one scene folder:

    scene_camera.json   {im_id: {cam_K, depth_scale[, cam_R_w2c, cam_t_w2c]}}
    scene_gt.json       {im_id: [{obj_id, cam_R_m2c, cam_t_m2c}, ...]}
    scene_gt_info.json  {im_id: [{bbox_obj, bbox_visib, px_count_all, px_count_valid, px_count_visib,
                                  visib_fract}, ...]}
    rgb/{im_id:06d}.png|.jpg   (gray/ for grayscale sets)
    depth/{im_id:06d}.png      uint16 (.tif for ITODD)
    mask/{im_id:06d}_{gt_idx:06d}.png, mask_visib/{im_id:06d}_{gt_idx:06d}.png   (0 / 255)

Validation at the boundary (every failure is a `DatasetError` naming the file): scene_camera.json must map image
ids to entries with 9 finite `cam_K` values (plausible fx, fy > 0, last row 0 0 1, principal point inside the
image), a finite `depth_scale` in [MIN_DEPTH_SCALE_MM, MAX_DEPTH_SCALE_MM] (never defaulted), and, when given, an
orthonormal `cam_R_w2c` (det +1) with a finite `cam_t_w2c`. Image sizes are read from the file header before
decoding (at most `MAX_IMAGE_SIDE` pixels a side); depth must be a 16-bit single-channel PNG; saturated (65535)
and out-of-range (outside MIN_DEPTH_M..MAX_DEPTH_M) depths are masked with a warning, or refused when more than
`MAX_BAD_DEPTH_FRACTION` of the pixels are; a depth image with fewer than `MIN_VALID_DEPTH_FRACTION` valid pixels
is refused; a colour image that exists but does not decode is refused. A scene of a `normpos_grasp.sim` dataset
(models/ at the dataset root, scene_static.json in its scenes) whose root lacks camera.json or parts.json was not
finished (an interrupted `synth`) and is refused.
"""

from __future__ import annotations

import json
import logging
import math
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_bytes
from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.errors import DatasetError, InputError, MeshError
from normpos_grasp.io.ply import write_mesh_ply
from normpos_grasp.typing import ArrayLike, BoolArray, FloatArray, UInt8Array, UInt16Array
from normpos_grasp.validation import as_float_array, check_pose

logger = logging.getLogger(__name__)

_RGB_DIRS = ("rgb", "gray")
_RGB_EXTS = (".png", ".jpg", ".jpeg", ".tif")
_DEPTH_EXTS = (".png", ".tif")  # .tif: ITODD (bop_toolkit dataset_params: depth_ext 'tif', gray/ images in .tif)

#: largest image width or height read (pixels); checked from the header before decoding
MAX_IMAGE_SIDE = 8192
#: farthest plausible depth (metres): no RGB-D sensor used for bin picking measures beyond this
MAX_DEPTH_M = 10.0
#: raw depth value of a saturated pixel
SATURATED_DEPTH = 65535
#: more saturated or out-of-range pixels than this fraction of the image refuse the frame (fewer are masked)
MAX_BAD_DEPTH_FRACTION = 0.01
#: fewer valid depth pixels than this fraction of the image refuse the frame
MIN_VALID_DEPTH_FRACTION = 0.01
#: nearest plausible depth (metres): closer non-zero values are noise or a wrong depth_scale
MIN_DEPTH_M = 0.01
#: plausible depth_scale range (mm per raw unit) and largest camera distance from the world origin (mm)
MIN_DEPTH_SCALE_MM = 0.01
MAX_DEPTH_SCALE_MM = 100.0
MAX_CAMERA_DISTANCE_MM = 100_000.0


# --------------------------------------------------------------------------------------------------
# data types
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class BopGT:
    """One ground-truth object pose: `camera_from_object` (4, 4) in metres (BOP's x_cam = R x_model + t)."""

    obj_id: int
    camera_from_object: FloatArray

    def __post_init__(self) -> None:
        object.__setattr__(self, "obj_id", int(self.obj_id))
        object.__setattr__(self, "camera_from_object", check_pose(self.camera_from_object, "camera_from_object", 1e-4))

    @classmethod
    def from_bop(cls, entry: dict[str, Any]) -> BopGT:
        """From one `scene_gt.json` entry (R row-major, t in mm); the rotation is re-orthonormalised."""
        try:
            rot = np.asarray(entry["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
            t_mm = np.asarray(entry["cam_t_m2c"], dtype=np.float64).reshape(3)
            obj_id = int(entry["obj_id"])
        except (KeyError, ValueError, TypeError) as exc:
            raise DatasetError(
                f"scene_gt entry must hold obj_id, cam_R_m2c (9) and cam_t_m2c (3), got {entry}"
            ) from exc
        pose = np.eye(4)
        pose[:3, :3] = _orthonormalise(rot)
        pose[:3, 3] = t_mm / 1000.0
        return cls(obj_id, pose)

    def to_bop(self) -> dict[str, Any]:
        """One `scene_gt.json` entry (mm)."""
        return {
            "obj_id": self.obj_id,
            "cam_R_m2c": self.camera_from_object[:3, :3].reshape(-1).tolist(),
            "cam_t_m2c": (self.camera_from_object[:3, 3] * 1000.0).tolist(),
        }


@dataclass(frozen=True, eq=False)
class BopModel:
    """One object model as described by `models_info.json` (converted to metres).

    Attributes:
        obj_id: BOP object id.
        mesh_path: path of `obj_{obj_id:06d}.ply` (may not exist when only the info is present).
        diameter_m: largest distance between two model vertices, metres.
        extents_m: (3,) bounding-box size along the model axes, metres.
        min_m: (3,) bounding-box minimum corner, metres.
        symmetries_discrete: (K, 4, 4) poses `object_from_object` that map the model onto itself, metres.
        symmetries_continuous: tuple of (axis (3,) unit vector, offset (3,) metres): rotation about the axis
            through `offset` leaves the model unchanged.
    """

    obj_id: int
    mesh_path: Path
    diameter_m: float
    extents_m: FloatArray
    symmetries_discrete: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    symmetries_continuous: tuple[tuple[FloatArray, FloatArray], ...] = ()
    min_m: FloatArray = field(default_factory=lambda: np.full(3, np.nan))


# --------------------------------------------------------------------------------------------------
# models
# --------------------------------------------------------------------------------------------------
def read_models(models_dir: str | Path) -> dict[int, BopModel]:
    """Read `models_info.json` of a BOP `models/` folder; returns {obj_id: BopModel}, metres."""
    root = Path(models_dir)
    info = _read_json(root / "models_info.json")
    if not isinstance(info, dict):
        raise DatasetError(f"{root / 'models_info.json'}: expected an object keyed by obj_id")
    out: dict[int, BopModel] = {}
    for key, entry in info.items():
        obj_id = _int_key(key, root / "models_info.json")
        try:
            diameter = float(entry["diameter"]) / 1000.0
            size = np.array([entry["size_x"], entry["size_y"], entry["size_z"]], dtype=np.float64) / 1000.0
            mins = (
                np.array(
                    [entry.get("min_x", np.nan), entry.get("min_y", np.nan), entry.get("min_z", np.nan)],
                    dtype=np.float64,
                )
                / 1000.0
            )
            disc = [_sym_from_bop(s) for s in entry.get("symmetries_discrete", [])]
            cont = tuple(
                (
                    _unit(np.asarray(s["axis"], dtype=np.float64).reshape(3)),
                    np.asarray(s["offset"], dtype=np.float64).reshape(3) / 1000.0,
                )
                for s in entry.get("symmetries_continuous", [])
            )
        except (KeyError, ValueError, TypeError, AttributeError, InputError) as exc:
            raise DatasetError(
                f"models_info.json entry {key} must hold diameter, size_x/y/z and well-formed symmetries: {exc}"
            ) from exc
        if not (math.isfinite(diameter) and diameter > 0 and np.all(np.isfinite(size)) and np.all(size >= 0)):
            raise DatasetError(
                f"{root / 'models_info.json'} entry {key}: diameter must be a finite positive length and "
                f"size_x/y/z finite and >= 0 (mm), got diameter {entry.get('diameter')!r}, "
                f"size {[entry.get(k) for k in ('size_x', 'size_y', 'size_z')]}"
            )
        out[obj_id] = BopModel(
            obj_id=obj_id,
            mesh_path=root / f"obj_{obj_id:06d}.ply",
            diameter_m=diameter,
            extents_m=size,
            symmetries_discrete=np.array(disc).reshape(-1, 4, 4) if disc else np.zeros((0, 4, 4)),
            symmetries_continuous=cont,
            min_m=mins,
        )
    return dict(sorted(out.items()))


def load_mesh(model: BopModel) -> Any:
    """Load the model's PLY (mm) as a `trimesh.Trimesh` in metres; raises DatasetError when absent."""
    import trimesh

    if not model.mesh_path.is_file():
        raise DatasetError(f"model mesh {model.mesh_path} not found (models_info.json lists obj_id {model.obj_id})")
    try:
        mesh = trimesh.load(str(model.mesh_path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for broken files
        raise MeshError(f"cannot read {model.mesh_path}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0:
        raise MeshError(f"{model.mesh_path} holds no triangle mesh")
    mesh.apply_scale(0.001)
    return mesh


def write_models(
    models_dir: str | Path,
    models: Sequence[tuple[int, Any, ArrayLike | None, Sequence[tuple[ArrayLike, ArrayLike]] | None]],
) -> None:
    """Write `obj_XXXXXX.ply` (mm, binary, triangles: see `io.ply.write_mesh_ply`) and `models_info.json` for
    meshes given in metres.

    Args:
        models_dir: target folder (created).
        models: (obj_id, trimesh mesh in metres, discrete symmetries (K, 4, 4) metres or None,
            continuous symmetries [(axis (3,), offset (3,) metres)] or None).
    """
    root = Path(models_dir)
    root.mkdir(parents=True, exist_ok=True)
    info: dict[int, dict[str, Any]] = {}
    for obj_id, mesh, disc, cont in models:
        obj_id = int(obj_id)
        if obj_id < 0 or obj_id in info:
            raise InputError(f"obj_id must be unique and non-negative, got {obj_id}")
        verts = np.asarray(mesh.vertices, dtype=np.float64)
        if verts.ndim != 2 or len(verts) == 0 or not np.all(np.isfinite(verts)):
            raise MeshError(f"mesh of obj_id {obj_id} has no vertices or non-finite ones")
        # triangles only, no face properties (an STL's per-face attributes would break the BOP toolkit's reader)
        normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
        write_mesh_ply(root / f"obj_{obj_id:06d}.ply", verts * 1000.0, np.asarray(mesh.faces), normals)
        lo, hi = verts.min(axis=0), verts.max(axis=0)
        entry: dict[str, Any] = {"diameter": _diameter(verts) * 1000.0}
        for i, ax in enumerate("xyz"):
            entry[f"min_{ax}"] = lo[i] * 1000.0
            entry[f"size_{ax}"] = (hi[i] - lo[i]) * 1000.0
        if disc is not None:
            syms = np.asarray(disc, dtype=np.float64).reshape(-1, 4, 4)
            entry["symmetries_discrete"] = [_sym_to_bop(check_pose(s, "discrete symmetry", 1e-5)) for s in syms]
        if cont:
            entry["symmetries_continuous"] = [
                {
                    "axis": _unit(as_float_array(a, "symmetry axis", (3,))).tolist(),
                    "offset": (as_float_array(o, "symmetry offset", (3,)) * 1000.0).tolist(),
                }
                for a, o in cont
            ]
        info[obj_id] = entry
    _atomic_write(root / "models_info.json", _dump_keyed(info))


# --------------------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------------------
class BopScene:
    """Read access to one BOP scene folder; JSON files are read once, images on demand."""

    def __init__(self, scene_dir: str | Path) -> None:
        self.path = Path(scene_dir)
        if not self.path.is_dir():
            raise DatasetError(f"BOP scene folder {self.path} does not exist")
        try:
            self.scene_id = int(self.path.name)
        except ValueError:
            self.scene_id = 0
        cam = self.path / "scene_camera.json"
        if not cam.is_file():
            raise DatasetError(f"{self.path} is not a BOP scene: scene_camera.json is missing")
        _check_finished(self.path)
        table = _read_json(cam)
        if not isinstance(table, dict):
            raise DatasetError(f"{cam}: expected an object keyed by image id, got a JSON {type(table).__name__}")
        self._camera = {_int_key(k, cam): v for k, v in table.items()}
        if not self._camera:
            raise DatasetError(
                f"{cam} lists no frames: the scene is empty or its writer was interrupted; generate it again"
            )
        for im_id, entry in self._camera.items():
            if not isinstance(entry, dict):
                raise DatasetError(f"{cam} frame {im_id}: expected an object (cam_K, depth_scale, ...), got {entry!r}")
        self._checked: dict[int, dict[str, Any]] = {}
        self._gt_raw: dict[int, list[dict[str, Any]]] | None = None
        self._gt_info_raw: dict[int, list[dict[str, Any]]] | None = None

    def __repr__(self) -> str:
        return f"BopScene({str(self.path)!r}, {len(self._camera)} frames)"

    @property
    def frame_ids(self) -> list[int]:
        """Sorted image ids listed in scene_camera.json."""
        return sorted(self._camera)

    def _check_id(self, im_id: int) -> int:
        if int(im_id) not in self._camera:
            raise DatasetError(
                f"image {im_id} is not in {self.path / 'scene_camera.json'} (ids: {self.frame_ids[:10]})"
            )
        return int(im_id)

    def rgb_path(self, im_id: int) -> Path:
        im_id = self._check_id(im_id)
        for sub in _RGB_DIRS:
            for ext in _RGB_EXTS:
                p = self.path / sub / f"{im_id:06d}{ext}"
                if p.is_file():
                    return p
        raise DatasetError(f"no colour image for frame {im_id} under {self.path}/rgb or /gray")

    def depth_path(self, im_id: int) -> Path:
        """depth/{im_id:06d}.png, or .tif (ITODD's layout)."""
        stem = self.path / "depth" / f"{self._check_id(im_id):06d}"
        for ext in _DEPTH_EXTS:
            if stem.with_suffix(ext).is_file():
                return stem.with_suffix(ext)
        raise DatasetError(f"depth image {stem.with_suffix('.png')} not found")

    def image_size(self, im_id: int) -> tuple[int, int]:
        """(width, height) of the frame, read from the image header."""
        for getter in (self.rgb_path, self.depth_path):
            try:
                path = getter(im_id)
            except DatasetError:
                continue
            return _image_size(path)
        raise DatasetError(f"frame {im_id} of {self.path} has neither a colour nor a depth image")

    def camera(self, im_id: int) -> Camera:
        """Camera of frame `im_id` (size from the image; extrinsics when cam_R_w2c/cam_t_w2c are given).

        Raises DatasetError when the scene_camera.json entry is malformed or implausible (see the module doc).
        """
        im_id = self._check_id(im_id)
        w, h = self.image_size(im_id)
        entry = self.camera_entry(im_id, (w, h))
        try:
            return Camera.from_bop(entry, w, h)
        except InputError as exc:
            raise DatasetError(f"{self.path / 'scene_camera.json'} frame {im_id}: {exc}") from exc

    def camera_entry(self, im_id: int, size: tuple[int, int] | None = None) -> dict[str, Any]:
        """The validated scene_camera.json entry of frame `im_id` (floats; cam_R_w2c re-orthonormalised).

        size: (width, height) to check the principal point against; read from the image header when None.
        """
        im_id = self._check_id(im_id)
        if im_id not in self._checked:
            w, h = self.image_size(im_id) if size is None else size
            self._checked[im_id] = _checked_camera_entry(
                self._camera[im_id], w, h, f"{self.path / 'scene_camera.json'} frame {im_id}"
            )
        return self._checked[im_id]

    def load_rgb(self, im_id: int) -> UInt8Array:
        """(H, W, 3) uint8 RGB (grayscale images are replicated to 3 channels); DatasetError when it does not decode."""
        path = self.rgb_path(im_id)
        img = _imread(path)
        if img.dtype != np.uint8:
            img = (img / max(float(img.max()), 1.0) * 255.0).astype(np.uint8)
        if img.ndim == 2:
            return np.repeat(img[:, :, None], 3, axis=2)
        if img.ndim != 3 or img.shape[2] not in (3, 4):
            raise DatasetError(f"{path}: expected a colour or grayscale image, got shape {img.shape}")
        if img.shape[2] == 4:
            img = img[:, :, :3]
        return np.ascontiguousarray(img[:, :, ::-1])

    def load_depth_raw(self, im_id: int) -> UInt16Array:
        """(H, W) uint16 raw depth as stored; DatasetError unless a 16-bit single-channel PNG (or TIFF, as ITODD)."""
        path = self.depth_path(im_id)
        header = _read_header(path)
        if path.suffix == ".tif":
            img = _imread(path)
            if img.ndim != 2 or img.dtype != np.uint16:
                raise DatasetError(
                    f"{path} decodes as {img.dtype} {img.shape}; BOP depth must be 16-bit single-channel "
                    "(raw units times depth_scale = mm)"
                )
            return np.asarray(img, dtype=np.uint16)
        if header.kind != "png":
            raise DatasetError(f"{path} is not a PNG file; BOP depth is a 16-bit single-channel PNG")
        if header.bit_depth != 16 or header.channels != 1:
            raise DatasetError(
                f"{path} is a {header.bit_depth}-bit PNG with {header.channels} channel(s); BOP depth must be "
                "16-bit single-channel (raw units times depth_scale = mm)"
            )
        img = _imread(path)
        if img.ndim != 2 or img.dtype != np.uint16:
            raise DatasetError(f"{path} must be a single-channel 16-bit PNG, decoded as {img.dtype} {img.shape}")
        return np.asarray(img, dtype=np.uint16)

    def depth_scale_mm(self, im_id: int) -> float:
        """The frame's depth_scale (mm per raw depth unit), validated (present, finite, > 0)."""
        im_id = self._check_id(im_id)
        entry = self._camera[im_id]
        where = f"{self.path / 'scene_camera.json'} frame {im_id}"
        return _depth_scale(entry, where)

    def load_depth(self, im_id: int) -> FloatArray:
        """(H, W) float64 depth in metres, 0 where invalid (depth_scale honoured).

        Saturated (65535) and implausibly far (> MAX_DEPTH_M) pixels are set to 0 with a warning; a frame where
        more than MAX_BAD_DEPTH_FRACTION of the pixels are, or fewer than MIN_VALID_DEPTH_FRACTION have depth, is
        refused with DatasetError.
        """
        im_id = self._check_id(im_id)
        scale_m = self.depth_scale_mm(im_id) / 1000.0
        raw = self.load_depth_raw(im_id)
        return _plausible_depth(raw, scale_m, self.depth_path(im_id))

    def load_frame(self, im_id: int) -> RGBDFrame:
        """The whole frame; a scene without colour images gives a black one (depth-only sets).

        A colour image that exists but cannot be decoded is an error, not a black image.
        """
        cam = self.camera(im_id)
        depth = self.load_depth(im_id)
        if self._has_rgb(im_id):
            rgb = self.load_rgb(im_id)
        else:
            logger.info("frame %d of %s has no colour image: using a black one", im_id, self.path)
            rgb = np.zeros((cam.height, cam.width, 3), dtype=np.uint8)
        if depth.shape != (cam.height, cam.width) or rgb.shape[:2] != depth.shape:
            raise DatasetError(f"frame {im_id} of {self.path}: colour {rgb.shape[:2]} and depth {depth.shape} differ")
        return RGBDFrame(rgb, depth, cam, stamp=0.0, scene_id=self.scene_id, im_id=int(im_id))

    def check_frame(self, im_id: int) -> None:
        """Validate frame `im_id` without decoding pixels: camera entry, depth_scale, image headers and sizes."""
        im_id = self._check_id(im_id)
        cam = self.camera(im_id)
        self.depth_scale_mm(im_id)
        depth = _read_header(self.depth_path(im_id))
        if depth.kind == "png" and (depth.bit_depth != 16 or depth.channels != 1):
            raise DatasetError(
                f"{self.depth_path(im_id)} is a {depth.bit_depth}-bit PNG with {depth.channels} channel(s); "
                "BOP depth must be 16-bit single-channel"
            )
        if (depth.width, depth.height) != (cam.width, cam.height):
            raise DatasetError(
                f"frame {im_id} of {self.path}: depth is {depth.width}x{depth.height}, colour {cam.width}x{cam.height}"
            )

    def _has_rgb(self, im_id: int) -> bool:
        try:
            self.rgb_path(im_id)
        except DatasetError:
            return False
        return True

    # -- ground truth ---------------------------------------------------------------------------
    def _gt_all(self) -> dict[int, list[dict[str, Any]]]:
        if self._gt_raw is None:
            path = self.path / "scene_gt.json"
            if not path.is_file():
                raise DatasetError(f"{path} not found: this scene has no ground truth")
            self._gt_raw = _keyed_lists(_read_json(path), path)
        return self._gt_raw

    def gt(self, im_id: int) -> list[BopGT]:
        """Ground-truth poses of frame `im_id`, in scene_gt.json order (the gt index of the masks)."""
        return [BopGT.from_bop(e) for e in self._gt_all().get(self._check_id(im_id), [])]

    def gt_info(self, im_id: int) -> list[dict[str, Any]]:
        """The frame's scene_gt_info.json entries (bbox [x, y, w, h] in pixels, pixel counts, visib_fract)."""
        if self._gt_info_raw is None:
            path = self.path / "scene_gt_info.json"
            if not path.is_file():
                raise DatasetError(f"{path} not found: run a BOP toolkit or BopSceneWriter to create it")
            self._gt_info_raw = _keyed_lists(_read_json(path), path)
        return [dict(e) for e in self._gt_info_raw.get(self._check_id(im_id), [])]

    def mask_visib(self, im_id: int, gt_index: int) -> BoolArray:
        """(H, W) bool visible-pixel mask of GT `gt_index` in frame `im_id`."""
        return self._mask("mask_visib", im_id, gt_index)

    def mask(self, im_id: int, gt_index: int) -> BoolArray:
        """(H, W) bool full silhouette (occluded parts included) of GT `gt_index`."""
        return self._mask("mask", im_id, gt_index)

    def has_masks(self, im_id: int, visib: bool = True) -> bool:
        sub = "mask_visib" if visib else "mask"
        return (self.path / sub / f"{self._check_id(im_id):06d}_{0:06d}.png").is_file()

    def _mask(self, sub: str, im_id: int, gt_index: int) -> BoolArray:
        path = self.path / sub / f"{self._check_id(im_id):06d}_{int(gt_index):06d}.png"
        if not path.is_file():
            raise DatasetError(f"mask {path} not found")
        img = _imread(path)
        if img.ndim == 3:
            img = img[:, :, 0]
        return np.asarray(img > 0)


def read_split(split_dir: str | Path) -> list[BopScene]:
    """All scenes (numeric sub-folders with scene_camera.json) of a BOP split folder, sorted by scene id."""
    root = Path(split_dir)
    if not root.is_dir():
        raise DatasetError(f"BOP split folder {root} does not exist")
    scenes = [
        BopScene(p)
        for p in sorted(root.iterdir(), key=lambda p: p.name)
        if p.is_dir() and p.name.isdigit() and (p / "scene_camera.json").is_file()
    ]
    if not scenes:
        raise DatasetError(f"{root} holds no BOP scene folders (numeric names with scene_camera.json)")
    return sorted(scenes, key=lambda s: s.scene_id)


def is_scene_dir(path: str | Path) -> bool:
    """True when `path` looks like one BOP scene folder (has scene_camera.json)."""
    return (Path(path) / "scene_camera.json").is_file()


# --------------------------------------------------------------------------------------------------
# writer
# --------------------------------------------------------------------------------------------------
class BopSceneWriter:
    """Write frames into a BOP scene folder; `close()` writes the JSON files atomically.

    Output is deterministic: the same frames give byte-identical files (sorted keys, floats rounded to
    fixed precision, PNG written with a fixed compression level). Use as a context manager or call close().
    """

    def __init__(self, scene_dir: str | Path, depth_scale_mm: float = 0.1) -> None:
        if not depth_scale_mm > 0:
            raise InputError(f"depth_scale_mm must be positive (mm per depth unit), got {depth_scale_mm}")
        self.path = Path(scene_dir)
        self.depth_scale_mm = float(depth_scale_mm)
        for sub in ("rgb", "depth", "mask", "mask_visib"):
            (self.path / sub).mkdir(parents=True, exist_ok=True)
        self._camera: dict[int, dict[str, Any]] = {}
        self._gt: dict[int, list[dict[str, Any]]] = {}
        self._gt_info: dict[int, list[dict[str, Any]]] = {}
        self._closed = False

    def __enter__(self) -> BopSceneWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def add_frame(
        self,
        im_id: int,
        rgb: UInt8Array,
        depth_m: FloatArray,
        camera: Camera,
        gts: Sequence[BopGT],
        masks: Sequence[BoolArray],
        masks_visib: Sequence[BoolArray],
    ) -> None:
        """Write one frame's images and masks and record its JSON entries.

        Args:
            im_id: non-negative image id, unique in this scene.
            rgb: (H, W, 3) uint8 RGB.
            depth_m: (H, W) depth in metres; NaN, inf, <= 0 are written as 0 (invalid).
            camera: the frame's camera (no distortion: BOP has no field for it).
            gts: ground-truth poses; masks and masks_visib: one (H, W) bool mask each, same order.
        """
        import cv2

        if self._closed:
            raise InputError("BopSceneWriter is closed")
        im_id = int(im_id)
        if im_id < 0 or im_id in self._camera:
            raise InputError(f"im_id must be non-negative and unique in the scene, got {im_id}")
        h, w = camera.height, camera.width
        rgb_arr = np.asarray(rgb)
        if rgb_arr.shape != (h, w, 3) or rgb_arr.dtype != np.uint8:
            raise InputError(f"rgb must be uint8 (H, W, 3) = ({h}, {w}, 3), got {rgb_arr.dtype} {rgb_arr.shape}")
        depth = np.asarray(depth_m, dtype=np.float64)
        if depth.shape != (h, w):
            raise InputError(f"depth_m must be (H, W) = ({h}, {w}), got {depth.shape}")
        if camera.has_distortion:
            raise InputError("BOP stores no distortion: undistort the images and pass a camera with zero distortion")
        if not (len(gts) == len(masks) == len(masks_visib)):
            raise InputError(
                f"need one mask and one visible mask per GT, got {len(gts)}, {len(masks)}, {len(masks_visib)}"
            )
        valid = np.isfinite(depth) & (depth > 0)
        raw = np.zeros((h, w), dtype=np.float64)
        raw[valid] = np.rint(depth[valid] * 1000.0 / self.depth_scale_mm)
        if raw.max(initial=0.0) > 65535:
            raise InputError(
                f"depth {depth[valid].max():.3f} m overflows uint16 at depth_scale {self.depth_scale_mm} mm; "
                "use a larger depth_scale_mm"
            )
        raw16 = raw.astype(np.uint16)
        valid_raw = raw16 > 0
        png = [cv2.IMWRITE_PNG_COMPRESSION, 3]
        _imwrite(self.path / "rgb" / f"{im_id:06d}.png", np.ascontiguousarray(rgb_arr[:, :, ::-1]), png)
        _imwrite(self.path / "depth" / f"{im_id:06d}.png", raw16, png)
        infos = []
        for idx, (m, mv) in enumerate(zip(masks, masks_visib, strict=True)):
            m_arr, mv_arr = np.asarray(m), np.asarray(mv)
            for name, arr in (("mask", m_arr), ("mask_visib", mv_arr)):
                if arr.shape != (h, w) or arr.dtype != np.bool_:
                    raise InputError(f"{name} {idx} must be bool (H, W) = ({h}, {w}), got {arr.dtype} {arr.shape}")
            _imwrite(self.path / "mask" / f"{im_id:06d}_{idx:06d}.png", m_arr.astype(np.uint8) * 255, png)
            _imwrite(self.path / "mask_visib" / f"{im_id:06d}_{idx:06d}.png", mv_arr.astype(np.uint8) * 255, png)
            n_all = int(m_arr.sum())
            n_vis = int(mv_arr.sum())
            infos.append(
                {
                    "bbox_obj": _bbox(m_arr),
                    "bbox_visib": _bbox(mv_arr),
                    "px_count_all": n_all,
                    "px_count_valid": int((mv_arr & valid_raw).sum()),
                    "px_count_visib": n_vis,
                    "visib_fract": n_vis / n_all if n_all > 0 else 0.0,
                }
            )
        entry = camera.to_bop()
        entry["depth_scale"] = self.depth_scale_mm
        self._camera[im_id] = entry
        self._gt[im_id] = [g.to_bop() for g in gts]
        self._gt_info[im_id] = infos

    def close(self) -> None:
        """Write scene_camera.json, scene_gt.json and scene_gt_info.json (atomic renames). Idempotent."""
        if self._closed:
            return
        _atomic_write(self.path / "scene_camera.json", _dump_keyed(self._camera))
        _atomic_write(self.path / "scene_gt.json", _dump_keyed(self._gt))
        _atomic_write(self.path / "scene_gt_info.json", _dump_keyed(self._gt_info))
        self._closed = True


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------
def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise DatasetError(f"{path} not found") from exc
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc


def _int_key(key: str, path: Path) -> int:
    try:
        return int(key)
    except ValueError as exc:
        raise DatasetError(f"{path}: keys must be integer ids, got {key!r}") from exc


def _orthonormalise(rot: FloatArray) -> FloatArray:
    u, _, vt = np.linalg.svd(rot)
    r = u @ vt
    if np.linalg.det(r) < 0:
        raise DatasetError(f"rotation has det < 0 (a reflection): {rot.tolist()}")
    return r


def _unit(v: FloatArray) -> FloatArray:
    n = float(np.linalg.norm(v))
    if not n > 1e-12:
        raise InputError(f"symmetry axis must be non-zero, got {v.tolist()}")
    return v / n


def _sym_from_bop(values: Any) -> FloatArray:
    pose = np.asarray(values, dtype=np.float64).reshape(4, 4).copy()
    pose[:3, 3] /= 1000.0
    pose[:3, :3] = _orthonormalise(pose[:3, :3])
    return pose


def _sym_to_bop(pose: FloatArray) -> list[float]:
    out = pose.copy()
    out[:3, 3] *= 1000.0
    return [float(v) for v in out.reshape(-1)]


def _diameter(verts: FloatArray) -> float:
    """Largest vertex-to-vertex distance (on convex-hull vertices when the hull can be built), metres."""
    pts = verts
    if len(verts) > 200:
        try:
            from scipy.spatial import ConvexHull

            pts = verts[ConvexHull(verts).vertices]
        except Exception:  # qhull fails on flat sets; fall back to all vertices
            pts = verts
    best = 0.0
    for start in range(0, len(pts), 2048):
        block = pts[start : start + 2048]
        d2 = ((block[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
        best = max(best, float(d2.max()))
    return math.sqrt(best)


def _bbox(mask: BoolArray) -> list[int]:
    """[x, y, w, h] of the True pixels; [-1, -1, -1, -1] when empty (BOP convention)."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(xs.min()), int(ys.min())
    return [x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1]


def _round(value: Any) -> Any:
    """Round floats to 9 significant digits after the point for stable text; recurse into containers."""
    if isinstance(value, float | np.floating):
        v = float(value)
        if not math.isfinite(v):
            raise InputError(f"cannot write non-finite value {v} to a BOP file")
        r = round(v, 9)
        return 0.0 if r == 0 else r
    if isinstance(value, dict):
        return {str(k): _round(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_round(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return _round(value.tolist())
    return value


def _dump_keyed(table: dict[int, Any]) -> bytes:
    """JSON object keyed by integer ids in numeric order, values with sorted keys; deterministic bytes."""
    lines = [
        f"  {json.dumps(str(k))}: {json.dumps(_round(table[k]), sort_keys=True, separators=(', ', ': '))}"
        for k in sorted(table)
    ]
    return ("{\n" + ",\n".join(lines) + "\n}\n").encode() if lines else b"{}\n"


def _atomic_write(path: Path, data: bytes) -> None:
    atomic_write_bytes(path, data)


def _imwrite(path: Path, img: np.ndarray, params: list[int]) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", img, params)
    if not ok:
        raise DatasetError(f"cannot encode {path}")
    _atomic_write(path, buf.tobytes())


# -- reading and checking ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header says: kind ('png', 'jpeg' or 'other'), size in pixels, bits per sample and
    channels (None where the header was not parsed)."""

    kind: str
    width: int
    height: int
    bit_depth: int | None = None
    channels: int | None = None


_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _read_header(path: Path) -> ImageHeader:
    """Parse the size (and bit depth) of a PNG or JPEG from its header, without decoding; others are decoded.

    Raises DatasetError for an unreadable or truncated header and for a size over MAX_IMAGE_SIDE a side.
    """
    try:
        with path.open("rb") as fh:
            head = fh.read(33)
            header: ImageHeader | None = None
            if head[:8] == b"\x89PNG\r\n\x1a\n":
                if len(head) < 26 or head[12:16] != b"IHDR":
                    raise DatasetError(f"{path}: truncated or corrupt PNG header")
                w, h = struct.unpack(">II", head[16:24])
                header = ImageHeader("png", int(w), int(h), int(head[24]), _PNG_CHANNELS.get(int(head[25])))
            elif head[:2] == b"\xff\xd8":
                fh.seek(2)
                header = _jpeg_header(fh, path)
    except OSError as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc
    if header is None:
        img = _imread(path, checked=False)
        header = ImageHeader("other", int(img.shape[1]), int(img.shape[0]))
    if not (0 < header.width <= MAX_IMAGE_SIDE and 0 < header.height <= MAX_IMAGE_SIDE):
        raise DatasetError(
            f"{path}: the header claims {header.width}x{header.height} pixels; images must be 1..{MAX_IMAGE_SIDE} "
            "pixels a side (a corrupt or hostile file?)"
        )
    return header


def _jpeg_header(fh: Any, path: Path) -> ImageHeader:
    """Walk the JPEG markers up to the first start-of-frame; returns its size, precision and components."""
    for _ in range(10_000):
        marker = fh.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            break
        code = marker[1]
        if code in (0xD8, 0x01) or 0xD0 <= code <= 0xD7:
            continue
        length_bytes = fh.read(2)
        if len(length_bytes) < 2:
            break
        (length,) = struct.unpack(">H", length_bytes)
        if code in _JPEG_SOF:
            body = fh.read(6)
            if len(body) < 6:
                break
            precision, h, w, comps = struct.unpack(">BHHB", body)
            return ImageHeader("jpeg", int(w), int(h), int(precision), int(comps))
        if length < 2:
            break
        fh.seek(length - 2, 1)
    raise DatasetError(f"{path}: truncated or corrupt JPEG (no frame header)")


def _imread(path: Path, checked: bool = True) -> np.ndarray:
    """Decode an image unchanged (bit depth and channels kept); DatasetError when it cannot be decoded.

    checked: check the header size against MAX_IMAGE_SIDE first. PNG chunk checksums and JPEG end markers are
    verified before decoding, so a truncated or overwritten file is refused with one clear message (and the
    codec libraries print nothing).
    """
    import cv2

    header = _read_header(path) if checked else None
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from exc
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        _check_png_chunks(data, path)
    elif data[:2] == b"\xff\xd8" and data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
        raise DatasetError(f"cannot decode {path}: the JPEG is truncated (no end-of-image marker)")
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise DatasetError(f"cannot decode {path}: {' '.join(str(exc).split())}") from exc
    if img is None:
        raise DatasetError(f"cannot decode {path}: corrupt, truncated or not an image")
    if header is not None and (img.shape[1], img.shape[0]) != (header.width, header.height):
        raise DatasetError(
            f"{path}: decoded {img.shape[1]}x{img.shape[0]} pixels, its header says {header.width}x{header.height}"
        )
    return np.asarray(img)


def _check_png_chunks(data: bytes, path: Path) -> None:
    """Walk the PNG chunks: every length in bounds, every CRC right, IDAT present, IEND last."""
    pos, seen_idat = 8, False
    while True:
        if pos + 12 > len(data):
            raise DatasetError(f"cannot decode {path}: the PNG is truncated (no IEND chunk)")
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > len(data):
            raise DatasetError(f"cannot decode {path}: the PNG is truncated inside a {kind!r} chunk")
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(data[pos + 4 : end - 4]) != crc:
            raise DatasetError(f"cannot decode {path}: corrupt PNG ({kind.decode('latin-1')!r} chunk checksum)")
        seen_idat |= kind == b"IDAT"
        if kind == b"IEND":
            if not seen_idat:
                raise DatasetError(f"cannot decode {path}: the PNG holds no image data")
            return
        pos = end


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the image header (PNG, JPEG), else by decoding the image."""
    header = _read_header(path)
    return header.width, header.height


def _keyed_lists(table: Any, path: Path) -> dict[int, list[dict[str, Any]]]:
    """{im_id: [entry, ...]} of scene_gt.json / scene_gt_info.json, checked for structure."""
    if not isinstance(table, dict):
        raise DatasetError(f"{path}: expected an object keyed by image id, got a JSON {type(table).__name__}")
    out: dict[int, list[dict[str, Any]]] = {}
    for key, value in table.items():
        im_id = _int_key(key, path)
        if not isinstance(value, list) or not all(isinstance(e, dict) for e in value):
            raise DatasetError(f"{path} frame {key}: expected a list of objects, got {str(value)[:80]}")
        out[im_id] = value
    return out


def _numbers(entry: dict[str, Any], key: str, n: int, where: str) -> FloatArray:
    """entry[key] as n finite floats (a flat list of JSON numbers, or a nested row-major matrix)."""
    if key not in entry:
        raise DatasetError(f"{where}: {key} is missing")
    value = entry[key]
    if isinstance(value, list) and value and all(isinstance(row, list) for row in value):
        value = [v for row in value for v in row]  # a nested [[...], [...], [...]] matrix
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise DatasetError(f"{where}: {key} must be a list of {n} numbers, got {str(value)[:120]}")
    arr = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise DatasetError(f"{where}: {key} holds NaN or infinite values: {value}")
    return arr


def _depth_scale(entry: dict[str, Any], where: str) -> float:
    if "depth_scale" not in entry:
        raise DatasetError(
            f"{where}: depth_scale is missing; BOP needs it (mm per raw depth unit, e.g. 1.0 or 0.1) and a "
            "guessed scale would put every object at the wrong distance"
        )
    value = entry["depth_scale"]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DatasetError(f"{where}: depth_scale must be a number (mm per raw depth unit), got {value!r}")
    scale = float(value)
    if not (math.isfinite(scale) and MIN_DEPTH_SCALE_MM <= scale <= MAX_DEPTH_SCALE_MM):
        raise DatasetError(
            f"{where}: depth_scale must be finite and in [{MIN_DEPTH_SCALE_MM}, {MAX_DEPTH_SCALE_MM}] mm per raw "
            f"unit, got {value!r}"
        )
    return scale


def _checked_camera_entry(entry: dict[str, Any], width: int, height: int, where: str) -> dict[str, Any]:
    """Validate one scene_camera.json entry (see the module doc); returns a clean copy for Camera.from_bop."""
    k = _numbers(entry, "cam_K", 9, where).reshape(3, 3)
    if not (k[0, 0] > 0 and k[1, 1] > 0) or not np.allclose(k[2], [0.0, 0.0, 1.0], atol=1e-9):
        raise DatasetError(f"{where}: cam_K must hold fx, fy > 0 and the last row [0, 0, 1], got {k.tolist()}")
    fx, fy = float(k[0, 0]), float(k[1, 1])
    if not (0.04 * width <= fx <= 1000.0 * width and 0.5 <= fy / fx <= 2.0):
        raise DatasetError(
            f"{where}: focal lengths fx {fx:g}, fy {fy:g} px are implausible for a {width} px wide image "
            "(field of view between 0.1 and 170 degrees, fy/fx within 0.5..2)"
        )
    if not (0 <= k[0, 2] <= width and 0 <= k[1, 2] <= height):
        raise DatasetError(
            f"{where}: principal point ({k[0, 2]:g}, {k[1, 2]:g}) lies outside the {width}x{height} image"
        )
    out: dict[str, Any] = {"cam_K": k.reshape(-1).tolist(), "depth_scale": _depth_scale(entry, where)}
    has_r, has_t = "cam_R_w2c" in entry, "cam_t_w2c" in entry
    if has_r != has_t:
        raise DatasetError(f"{where}: cam_R_w2c and cam_t_w2c come together; only one of them is given")
    if has_r:
        rot = _numbers(entry, "cam_R_w2c", 9, where).reshape(3, 3)
        err = float(np.max(np.abs(rot @ rot.T - np.eye(3))))
        if err > 1e-3 or np.linalg.det(rot) <= 0:
            raise DatasetError(
                f"{where}: cam_R_w2c is not a rotation (|R R^T - I| = {err:.3g}, det {np.linalg.det(rot):.6g}); "
                "give 9 row-major values of an orthonormal matrix with det +1"
            )
        t = _numbers(entry, "cam_t_w2c", 3, where)
        if float(np.linalg.norm(t)) > MAX_CAMERA_DISTANCE_MM:
            raise DatasetError(
                f"{where}: cam_t_w2c {t.tolist()} mm puts the camera more than {MAX_CAMERA_DISTANCE_MM / 1000:g} m "
                "from the world origin; cam_t_w2c is in millimetres"
            )
        out["cam_R_w2c"] = rot.reshape(-1).tolist()
        out["cam_t_w2c"] = t.tolist()
    return out


def _plausible_depth(raw: UInt16Array, scale_m: float, path: Path) -> FloatArray:
    """Raw depth -> metres with saturated and out-of-range pixels masked (or the frame refused)."""
    n = raw.size
    saturated = raw == SATURATED_DEPTH
    depth = raw.astype(np.float64) * scale_m
    far = ((depth > MAX_DEPTH_M) | ((depth > 0) & (depth < MIN_DEPTH_M))) & ~saturated
    n_sat, n_far = int(saturated.sum()), int(far.sum())
    if n_sat > MAX_BAD_DEPTH_FRACTION * n:
        raise DatasetError(
            f"{path}: {n_sat} of {n} depth pixels ({100 * n_sat / n:.1f} %) are saturated ({SATURATED_DEPTH}); "
            "the depth is clipped or was written with the wrong scale"
        )
    if n_far > MAX_BAD_DEPTH_FRACTION * n:
        raise DatasetError(
            f"{path}: {n_far} of {n} depth pixels ({100 * n_far / n:.1f} %) lie beyond {MAX_DEPTH_M:g} m or "
            f"nearer than {MIN_DEPTH_M:g} m at depth_scale {scale_m * 1000:g} mm/unit; check depth_scale in "
            "scene_camera.json"
        )
    if n_sat or n_far:
        logger.warning(
            "%s: %d saturated and %d out-of-range (outside %g..%g m) depth pixels masked as invalid",
            path, n_sat, n_far, MIN_DEPTH_M, MAX_DEPTH_M,
        )  # fmt: skip
        depth[saturated | far] = 0.0
    n_valid = int(np.count_nonzero(depth))
    if n_valid < MIN_VALID_DEPTH_FRACTION * n:
        what = "no valid depth (all zero)" if n_valid == 0 else f"only {n_valid} of {n} pixels with depth"
        raise DatasetError(f"{path} has {what}; nothing can be measured in this frame")
    return depth


def _check_finished(scene_dir: Path) -> None:
    """Refuse a scene of a `normpos_grasp.sim` dataset whose writer did not finish (an interrupted `synth`).

    Such a dataset writes models/ first, scene_static.json into each finished scene, and camera.json plus
    parts.json at its root only once every scene is complete.
    """
    split = scene_dir.parent
    root = split.parent
    if not (root / "models" / "models_info.json").is_file():
        return  # not inside a dataset folder (for example a scene copied on its own)
    if not (scene_dir / "scene_static.json").is_file() and next(split.glob("*/scene_static.json"), None) is None:
        return
    missing = [name for name in ("camera.json", "parts.json") if not (root / name).is_file()]
    if missing:
        raise DatasetError(
            f"{root} is an incomplete synthetic dataset ({' and '.join(missing)} missing: its `synth` run was "
            "interrupted); generate it again"
        )
