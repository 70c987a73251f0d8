"""Instance-segmentation metrics: match predictions to ground truth by mask IoU (numpy only, no torch)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from normpos_grasp.records.instance import Instance
from normpos_grasp.typing import FloatArray


def mask_iou_matrix(a: list[np.ndarray], b: list[np.ndarray]) -> FloatArray:
    """(len(a), len(b)) IoU of (H, W) bool masks."""
    if not a or not b:
        return np.zeros((len(a), len(b)))
    fa = np.stack([m.ravel() for m in a]).astype(np.float32)
    fb = np.stack([m.ravel() for m in b]).astype(np.float32)
    inter = fa @ fb.T
    union = fa.sum(1)[:, None] + fb.sum(1)[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0).astype(np.float64)


@dataclass
class MatchStats:
    """Counts accumulated over frames; eligible GT: >= min_pixels visible pixels and visib_fract >= min_visib."""

    gt: int = 0
    pred: int = 0
    matched: int = 0
    ignored_pred: int = 0
    class_correct: int = 0
    ious: list[float] = field(default_factory=list)

    @property
    def recall(self) -> float:
        return self.matched / self.gt if self.gt else 1.0

    @property
    def precision(self) -> float:
        counted = self.pred - self.ignored_pred
        return self.matched / counted if counted > 0 else 1.0

    @property
    def mean_iou(self) -> float:
        return float(np.mean(self.ious)) if self.ious else 0.0

    @property
    def class_accuracy(self) -> float:
        return self.class_correct / self.matched if self.matched else 0.0

    def add(
        self,
        pred: list[Instance],
        gt: list[Instance],
        visib_fract: FloatArray,
        iou_threshold: float = 0.5,
        min_pixels: int = 400,
        min_visib: float = 0.3,
    ) -> None:
        """Match one frame: Hungarian assignment on IoU; predictions matching only ineligible GT are ignored."""
        eligible = np.array(
            [g.pixel_count >= min_pixels and v >= min_visib for g, v in zip(gt, visib_fract, strict=True)], bool
        )
        iou = mask_iou_matrix([g.mask for g in gt], [p.mask for p in pred])
        self.gt += int(eligible.sum())
        self.pred += len(pred)
        if not len(pred):
            return
        matched_pred = np.zeros(len(pred), bool)
        if eligible.any():
            sub = iou[eligible]
            rows, cols = linear_sum_assignment(-sub)
            gt_idx = np.flatnonzero(eligible)
            for r, c in zip(rows, cols, strict=True):
                if sub[r, c] >= iou_threshold:
                    self.matched += 1
                    matched_pred[c] = True
                    self.ious.append(float(sub[r, c]))
                    self.class_correct += int(pred[c].label == gt[gt_idx[r]].label)
        if (~eligible).any():
            best_inel = iou[~eligible].max(axis=0)
            self.ignored_pred += int(np.sum(~matched_pred & (best_inel >= iou_threshold)))
