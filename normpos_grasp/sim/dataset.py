"""Synthetic frames with ground truth, in memory (`generate_frame`) or written as a BOP dataset.

Seeding: a scene's layout comes from `SceneOptions.seed`; a frame's camera pose and sensor noise from the
frame seed. `write_bop_dataset` derives every scene and frame seed from its one `seed`, so the same call
writes byte-identical files.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_text
from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.errors import InputError
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.template import Template
from normpos_grasp.sim.cameras import CameraOptions, sample_camera
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.render import Rendering, SceneRenderer, make_renderer
from normpos_grasp.sim.scene import SceneLayout, SceneOptions, compose_scene
from normpos_grasp.sim.sensor import SensorModel, sensor_preset
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]


@dataclass(frozen=True, eq=False)
class SyntheticFrame:
    """One simulated frame and its truth.

    frame: what the sensor delivers (noisy RGB-D, camera with world_from_camera).
    layout: the scene; rendering: the ideal images (depth, instance ids, full and visible masks).
    instances: ground-truth instances of the parts with visible pixels (label = part label, score 1,
        instance_id = part index + 1, source_id = part index).
    world_from_object: (N, 4, 4) part poses, metres; visib_fractions: (N,) visible / full pixels per part.
    """

    frame: RGBDFrame
    layout: SceneLayout
    rendering: Rendering
    instances: list[Instance]
    world_from_object: FloatArray
    visib_fractions: FloatArray
    sensor: SensorModel

    @property
    def camera(self) -> Camera:
        return self.frame.camera


def _as_sensor(sensor: SensorModel | str) -> SensorModel:
    return sensor_preset(sensor) if isinstance(sensor, str) else sensor


def ground_truth_instances(layout: SceneLayout, rendering: Rendering) -> list[Instance]:
    """Instances (visible masks) of every part with at least one visible pixel, in part order."""
    out = []
    for k, t in enumerate(layout.templates):
        mask = rendering.masks_visible[k]
        if mask.any():
            out.append(Instance(mask=mask.copy(), label=t.label, score=1.0, instance_id=k + 1, source_id=k))
    return out


def render_frame(
    layout: SceneLayout,
    renderer: SceneRenderer,
    camera: Camera,
    sensor: SensorModel,
    rng: np.random.Generator,
    scene_id: int = 0,
    im_id: int = 0,
) -> SyntheticFrame:
    """Render `layout` through `camera` with `renderer` and pass it through `sensor` (noise from `rng`)."""
    rendering = renderer.render(camera)
    rgb, depth = sensor.apply(rendering, camera, rng)
    frame = RGBDFrame(rgb=rgb, depth_m=depth, camera=camera, stamp=0.0, scene_id=scene_id, im_id=im_id)
    return SyntheticFrame(
        frame=frame,
        layout=layout,
        rendering=rendering,
        instances=ground_truth_instances(layout, rendering),
        world_from_object=layout.world_from_object.copy(),
        visib_fractions=rendering.visib_fractions,
        sensor=sensor,
    )


def generate_frame(
    options: SceneOptions,
    sensor: SensorModel | str,
    camera_options: CameraOptions,
    seed: int,
    library: list[Template] | None = None,
    backend: str = "auto",
) -> SyntheticFrame:
    """Compose the scene of `options` (seeded by options.seed), view it from a camera drawn with `seed`, add noise.

    library: part templates (default: `default_part_library()`); backend: renderer ('auto', 'mujoco', 'raycast').
    """
    sensor_model = _as_sensor(sensor)
    layout = compose_scene(options, default_part_library() if library is None else library)
    rng = np.random.default_rng(seed)
    camera = sample_camera(camera_options, layout.container_centre(), rng)
    renderer = make_renderer(layout, camera.width, camera.height, backend)
    try:
        return render_frame(layout, renderer, camera, sensor_model, rng)
    finally:
        renderer.close()


# -- BOP export ------------------------------------------------------------------------------
def _scene_seed(seed: int, scene_index: int) -> int:
    return int(np.random.SeedSequence([int(seed), int(scene_index), 0x5CE]).generate_state(1)[0])


def _dump(data: Any) -> str:
    return json.dumps(data, indent=2, sort_keys=True) + "\n"


def write_bop_dataset(
    out_dir: str | Path,
    n_scenes: int,
    n_frames: int,
    sensor: SensorModel | str = "d435",
    resolution: tuple[int, int] = (640, 480),
    parts: Sequence[str] | Sequence[Template] | None = None,
    seed: int = 0,
    progress: ProgressFn | None = None,
    scene_options: SceneOptions | None = None,
    camera_options: CameraOptions | None = None,
    split: str = "train",
    backend: str = "auto",
    resume: bool = False,
    library: Sequence[Template] | None = None,
) -> Path:
    """Write `n_scenes` scenes of `n_frames` views each as a BOP dataset under `out_dir`; returns the split folder.

    Layout: models/ (obj_XXXXXX.ply in mm, models_info.json), {split}/{scene:06d}/ (rgb, depth, mask,
    mask_visib, scene_camera.json with cam_R_w2c/cam_t_w2c, scene_gt.json, scene_gt_info.json,
    scene_static.json with the static boxes in mm), camera.json and parts.json (obj_id -> part name).
    library: the part library (default: `default_part_library()`); parts: names from it, Templates, or None for
    the whole library. A part's obj_id is its template's `obj_id` (the built-in parts' are fixed, 1..8), so ids
    survive into estimate results; a template without one gets the smallest id not taken, in order.
    progress(frames_done, frames_total) is called after every frame.

    Each scene is written into `{split}/.{scene:06d}.partial` and renamed to its folder when complete, and
    parts.json (which readers require) is written last. resume: keep the scene folders an earlier, interrupted
    call with the same arguments finished and write only the others (scenes and frames are seeded
    independently, so the files equal those of one uninterrupted call).
    """
    import shutil

    from normpos_grasp.io.bop import BopGT, BopSceneWriter, write_models
    from normpos_grasp.sim.cameras import camera_intrinsics

    if n_scenes < 1 or n_frames < 1:
        raise InputError(f"need at least one scene and one frame, got {n_scenes} scenes x {n_frames} frames")
    sensor_model = _as_sensor(sensor)
    library = _resolve_parts(parts, library)
    obj_ids = part_obj_ids(library)
    base_scene = scene_options if scene_options is not None else SceneOptions()
    base_scene = replace(base_scene, parts=tuple(t.name for t in library))
    cam_opts = camera_options if camera_options is not None else CameraOptions(sensor=_intrinsics_name(sensor_model))
    cam_opts = replace(cam_opts, resolution=tuple(resolution))  # type: ignore[arg-type]
    root = Path(out_dir)
    split_dir = root / split
    split_dir.mkdir(parents=True, exist_ok=True)
    write_models(
        root / "models",
        [
            (obj_ids[t.name], t.mesh, np.asarray(t.symmetry.discrete).reshape(-1, 4, 4), list(t.symmetry.continuous))
            for t in library
        ],
    )
    depth_scale_mm = 0.1 if sensor_model.max_range_m <= 6.5 else 1.0
    total = n_scenes * n_frames
    done = 0
    for s in range(n_scenes):
        scene_dir = split_dir / f"{s:06d}"
        if resume and scene_dir.is_dir():
            done += n_frames
            if progress is not None:
                progress(done, total)
            continue
        staging = split_dir / f".{s:06d}.partial"
        if staging.exists():  # left by an interrupted call
            shutil.rmtree(staging)
        layout = compose_scene(replace(base_scene, seed=_scene_seed(seed, s)), library)
        if not layout.settled:
            logger.info("scene %d: parts had not fully come to rest after %.1f s", s, layout.settle_time_s)
        renderer = make_renderer(layout, resolution[0], resolution[1], backend)
        try:
            with BopSceneWriter(staging, depth_scale_mm=depth_scale_mm) as writer:
                for f in range(n_frames):
                    rng = np.random.default_rng([int(seed), s, f, 0xF4A])
                    camera = sample_camera(cam_opts, layout.container_centre(), rng)
                    camera = Camera(
                        camera.K,
                        camera.width,
                        camera.height,
                        camera.distortion,
                        depth_scale_mm / 1000.0,
                        camera.world_from_camera,
                    )
                    sf = render_frame(layout, renderer, camera, sensor_model, rng, scene_id=s, im_id=f)
                    cfw = camera.camera_from_world
                    gts = [
                        BopGT(obj_ids[t.name], cfw @ layout.world_from_object[k])
                        for k, t in enumerate(layout.templates)
                    ]
                    writer.add_frame(
                        f,
                        sf.frame.rgb,
                        sf.frame.depth_m,
                        camera,
                        gts,
                        list(sf.rendering.masks),
                        list(sf.rendering.masks_visible),
                    )
                    done += 1
                    if progress is not None:
                        progress(done, total)
        finally:
            renderer.close()
        (staging / "scene_static.json").write_text(_dump(_static_json(layout)))
        if scene_dir.exists():  # an earlier scene folder when not resuming
            shutil.rmtree(scene_dir)
        staging.replace(scene_dir)  # the finished scene appears at once
    intrinsics = camera_intrinsics(cam_opts.sensor, cam_opts.resolution)  # every frame's (poses vary)
    k = intrinsics.K
    cam_json = {
        "cx": float(k[0, 2]),
        "cy": float(k[1, 2]),
        "fx": float(k[0, 0]),
        "fy": float(k[1, 1]),
        "width": intrinsics.width,
        "height": intrinsics.height,
        "depth_scale": depth_scale_mm,
    }
    atomic_write_text(root / "camera.json", _dump(cam_json))
    info = {
        "generator": "normpos_grasp.sim",
        "sensor": sensor_model.name,
        "resolution": list(resolution),
        "seed": int(seed),
        "scenes": n_scenes,
        "frames_per_scene": n_frames,
        "container": base_scene.container,
        "parts": {str(obj_ids[t.name]): {"name": t.name, "label": t.label, "shape": t.shape} for t in library},
    }
    atomic_write_text(root / "parts.json", _dump(info))  # last: the dataset is complete
    return split_dir


def _intrinsics_name(sensor: SensorModel) -> str:
    from normpos_grasp.sim.cameras import INTRINSICS

    return sensor.name if sensor.name in INTRINSICS else "d435"


def part_obj_ids(parts: Sequence[Template]) -> dict[str, int]:
    """name -> BOP obj_id: each template's own `obj_id`; those without one (-1) get the smallest free ids in order.

    Raises InputError when two parts declare the same obj_id.
    """
    taken: dict[int, str] = {}
    for t in parts:
        if t.obj_id >= 0:
            if t.obj_id in taken and taken[t.obj_id] != t.name:
                raise InputError(f"parts '{taken[t.obj_id]}' and '{t.name}' both have obj_id {t.obj_id}")
            taken[t.obj_id] = t.name
    out = {t.name: t.obj_id for t in parts if t.obj_id >= 0}
    free = 1
    for t in parts:
        if t.name not in out:
            while free in taken:
                free += 1
            out[t.name] = free
            taken[free] = t.name
    return out


def _resolve_parts(
    parts: Sequence[str] | Sequence[Template] | None, library: Sequence[Template] | None = None
) -> list[Template]:
    lib = list(default_part_library() if library is None else library)
    if parts is None or len(parts) == 0:
        return lib
    if all(isinstance(p, Template) for p in parts):
        return list(parts)  # type: ignore[arg-type]
    by_name = {t.name: t for t in lib}
    names = [str(p) for p in parts]
    missing = [n for n in names if n not in by_name]
    if missing:
        known = ", ".join(f"{t.name} ({t.obj_id})" for t in lib)
        raise InputError(f"unknown part names {missing}; the library holds {known}")
    return [by_name[n] for n in dict.fromkeys(names)]


def _static_json(layout: SceneLayout) -> dict[str, Any]:
    """Static boxes in BOP units: world_from_box as R_b2w (row-major) and t_b2w_mm, full size_mm (box centred)."""
    return {
        name: {
            "R_b2w": np.round(pose[:3, :3], 12).reshape(-1).tolist(),
            "t_b2w_mm": np.round(pose[:3, 3] * 1000.0, 6).tolist(),
            "size_mm": np.round(np.asarray(size) * 1000.0, 6).tolist(),
        }
        for name, pose, size in layout.static_boxes
    }
