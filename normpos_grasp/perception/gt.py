"""Ground-truth segmenter: instances from a BOP scene's `mask_visib/` (or rendered from its GT poses).

Makes measurement testable on its own. When the scene has no mask_visib PNGs (for example the LM-O
sample), masks can be rendered from the object models at their GT poses with BOP's visibility test
(a model pixel is visible when the measured depth is missing or at most `visib_delta_m` in front of it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.errors import DatasetError, InputError, SegmentationError
from normpos_grasp.io.bop import BopModel, BopScene, load_mesh, read_models
from normpos_grasp.records.instance import Instance

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class GroundTruthOptions:
    """Settings of `GroundTruthSegmenter`.

    Attributes:
        min_visible_px: GT objects with fewer visible pixels are left out.
        render_missing: render masks from the models when the scene lacks mask_visib PNGs.
        models_dir: BOP models folder for rendering; None looks for `<scene>/../../models`.
        visib_delta_m: BOP's visibility tolerance, metres.
    """

    min_visible_px: int = 1
    render_missing: bool = True
    models_dir: str | None = None
    visib_delta_m: float = 0.015


def label_for(obj_id: int) -> str:
    """Label given to BOP object `obj_id`: 'obj_000005'."""
    return f"obj_{int(obj_id):06d}"


class GroundTruthSegmenter:
    """Segmenter returning the GT visible masks of a BOP scene's frame (matched by `frame.im_id`).

    Instance labels are `obj_XXXXXX`, score 1.0, instance_id 1..N in GT order (skipping objects with too few
    visible pixels), source_id the GT index in scene_gt.json.
    """

    def __init__(self, scene: BopScene | str | Path, options: GroundTruthOptions | None = None) -> None:
        self.scene = scene if isinstance(scene, BopScene) else BopScene(scene)
        self.options = GroundTruthOptions() if options is None else options
        self._models: dict[int, BopModel] | None = None
        self._meshes: dict[int, Any] = {}

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        im_id = int(frame.im_id)
        if im_id not in self.scene.frame_ids:
            raise SegmentationError(f"frame im_id {im_id} is not in the GT scene {self.scene.path}")
        gts = self.scene.gt(im_id)
        h, w = frame.depth_m.shape
        if self.scene.has_masks(im_id, visib=True) or not gts:
            masks = [self.scene.mask_visib(im_id, i) for i in range(len(gts))]
        elif self.options.render_missing:
            masks = self._render_masks(frame, gts)
        else:
            raise SegmentationError(
                f"{self.scene.path} has no mask_visib for frame {im_id}; enable render_missing or write masks"
            )
        out: list[Instance] = []
        for idx, (gt, mask) in enumerate(zip(gts, masks, strict=True)):
            if mask.shape != (h, w):
                raise SegmentationError(f"mask {idx} of frame {im_id} is {mask.shape}, the frame is {(h, w)}")
            if int(mask.sum()) < self.options.min_visible_px:
                continue
            out.append(Instance(mask, label_for(gt.obj_id), 1.0, instance_id=len(out) + 1, source_id=idx))
        return out

    def _render_masks(self, frame: RGBDFrame, gts: list[Any]) -> list[np.ndarray]:
        from normpos_grasp.camera.render import render, visible_mask

        models = self._load_models()
        posed = []
        which = []
        for idx, gt in enumerate(gts):
            if gt.obj_id in models and models[gt.obj_id].mesh_path.is_file():
                if gt.obj_id not in self._meshes:
                    self._meshes[gt.obj_id] = load_mesh(models[gt.obj_id])
                posed.append((self._meshes[gt.obj_id], gt.camera_from_object))
                which.append(idx)
            else:
                logger.warning("no model for obj_id %d: its GT mask is left empty", gt.obj_id)
        h, w = frame.depth_m.shape
        masks = [np.zeros((h, w), dtype=bool) for _ in gts]
        if not posed:
            return masks
        rendering = render(frame.camera, posed)
        for k, idx in enumerate(which):
            model_depth = np.where(rendering.index == k, rendering.depth_m, 0.0)
            masks[idx] = visible_mask(model_depth, frame.depth_m, self.options.visib_delta_m)
        return masks

    def _load_models(self) -> dict[int, BopModel]:
        if self._models is None:
            root = (
                Path(self.options.models_dir)
                if self.options.models_dir is not None
                else self.scene.path.parent.parent / "models"
            )
            if not (root / "models_info.json").is_file():
                raise SegmentationError(
                    f"scene {self.scene.path} has no mask_visib and no models at {root} to render them from; "
                    "pass models_dir"
                )
            try:
                self._models = read_models(root)
            except (DatasetError, InputError) as exc:
                raise SegmentationError(f"cannot read models for GT masks: {exc}") from exc
        return self._models
