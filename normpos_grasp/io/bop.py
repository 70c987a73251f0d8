"""BOP dataset reader and writer (https://bop.felk.cvut.cz/ format): splits, scenes, frames, GT, masks, models.

Units: BOP files hold millimetres (poses, model vertices, models_info) and raw uint16 depth scaled by
`depth_scale` (mm per unit). Everything this module returns is in metres; conversion happens here only.

Layout of one scene folder:

    scene_camera.json   {im_id: {cam_K, depth_scale[, cam_R_w2c, cam_t_w2c]}}
    scene_gt.json       {im_id: [{obj_id, cam_R_m2c, cam_t_m2c}, ...]}
    scene_gt_info.json  {im_id: [{bbox_obj, bbox_visib, px_count_all, px_count_valid, px_count_visib,
                                  visib_fract}, ...]}
    rgb/{im_id:06d}.png|.jpg   (gray/ for grayscale sets)
    depth/{im_id:06d}.png      uint16
    mask/{im_id:06d}_{gt_idx:06d}.png, mask_visib/{im_id:06d}_{gt_idx:06d}.png   (0 / 255)
"""

from __future__ import annotations

import json
import logging
import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.errors import DatasetError, InputError, MeshError
from normpos_grasp.io.ply import write_mesh_ply
from normpos_grasp.typing import ArrayLike, BoolArray, FloatArray, UInt8Array, UInt16Array
from normpos_grasp.validation import as_float_array, check_pose

logger = logging.getLogger(__name__)

_RGB_DIRS = ("rgb", "gray")
_RGB_EXTS = (".png", ".jpg", ".jpeg", ".tif")


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
        except (KeyError, ValueError, TypeError) as exc:
            raise DatasetError(
                f"models_info.json entry {key} must hold diameter, size_x/y/z and well-formed symmetries: {exc}"
            ) from exc
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
        self._camera = {_int_key(k, cam): v for k, v in _read_json(cam).items()}
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
        p = self.path / "depth" / f"{self._check_id(im_id):06d}.png"
        if not p.is_file():
            raise DatasetError(f"depth image {p} not found")
        return p

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
        """Camera of frame `im_id` (size from the image; extrinsics when cam_R_w2c/cam_t_w2c are given)."""
        entry = self._camera[self._check_id(im_id)]
        w, h = self.image_size(im_id)
        try:
            return Camera.from_bop(entry, w, h)
        except InputError as exc:
            raise DatasetError(f"{self.path / 'scene_camera.json'} frame {im_id}: {exc}") from exc

    def load_rgb(self, im_id: int) -> UInt8Array:
        """(H, W, 3) uint8 RGB (grayscale images are replicated to 3 channels)."""
        import cv2

        path = self.rgb_path(im_id)
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"cannot decode {path}")
        if img.dtype != np.uint8:
            img = (img / max(float(img.max()), 1.0) * 255.0).astype(np.uint8)
        if img.ndim == 2:
            return np.repeat(img[:, :, None], 3, axis=2)
        if img.shape[2] == 4:
            img = img[:, :, :3]
        return np.ascontiguousarray(img[:, :, ::-1])

    def load_depth_raw(self, im_id: int) -> UInt16Array:
        """(H, W) uint16 raw depth as stored."""
        import cv2

        path = self.depth_path(im_id)
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2:
            raise DatasetError(f"{path} must be a single-channel 16-bit PNG")
        return img.astype(np.uint16, copy=False)

    def load_depth(self, im_id: int) -> FloatArray:
        """(H, W) float64 depth in metres, 0 where invalid (depth_scale honoured)."""
        raw = self.load_depth_raw(im_id)
        scale_mm = float(self._camera[int(im_id)].get("depth_scale", 1.0))
        return raw.astype(np.float64) * (scale_mm / 1000.0)

    def load_frame(self, im_id: int) -> RGBDFrame:
        """The whole frame; a missing colour image gives a black one (depth-only sets)."""
        cam = self.camera(im_id)
        depth = self.load_depth(im_id)
        try:
            rgb = self.load_rgb(im_id)
        except DatasetError:
            rgb = np.zeros((cam.height, cam.width, 3), dtype=np.uint8)
        if depth.shape != (cam.height, cam.width) or rgb.shape[:2] != depth.shape:
            raise DatasetError(f"frame {im_id} of {self.path}: colour {rgb.shape[:2]} and depth {depth.shape} differ")
        return RGBDFrame(rgb, depth, cam, stamp=0.0, scene_id=self.scene_id, im_id=int(im_id))

    # -- ground truth ---------------------------------------------------------------------------
    def _gt_all(self) -> dict[int, list[dict[str, Any]]]:
        if self._gt_raw is None:
            path = self.path / "scene_gt.json"
            if not path.is_file():
                raise DatasetError(f"{path} not found: this scene has no ground truth")
            self._gt_raw = {_int_key(k, path): list(v) for k, v in _read_json(path).items()}
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
            self._gt_info_raw = {_int_key(k, path): list(v) for k, v in _read_json(path).items()}
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
        import cv2

        path = self.path / sub / f"{self._check_id(im_id):06d}_{int(gt_index):06d}.png"
        if not path.is_file():
            raise DatasetError(f"mask {path} not found")
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(f"cannot decode {path}")
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
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


def _imwrite(path: Path, img: np.ndarray, params: list[int]) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", img, params)
    if not ok:
        raise DatasetError(f"cannot encode {path}")
    _atomic_write(path, buf.tobytes())


def _image_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG header, else by decoding the image."""
    with path.open("rb") as fh:
        head = fh.read(24)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"cannot decode {path}")
    return int(img.shape[1]), int(img.shape[0])
