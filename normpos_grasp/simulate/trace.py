"""Failure tracing in simulate: each failed pick and each part left in a bin gets a stage, a detail and a picture.

Stages (`STAGES`, in the pipeline's order): 'mask' (the segmenter missed the part or the chosen instance covers none),
'fit' (no accepted template fit, or a fit off the true pose by more than `SimulationConfig.wrong_fit_m`),
'no_feasible_grasp' (accepted fits, no grasp passed the planner; detail: the commonest rejection reason over the
parts left), 'path' (the hand hit something in physics on its way in, closing or lifting; detail: what it hit) and
'physics' (missed, dropped or slipped in MuJoCo; detail: the outcome). A part left in a bin is traced from the last
frame the scene saw: 'mask' when no instance covers it, 'fit' when its instance has no target, else its commonest
rejection reason; a scene that ended on failed picks in a row ('stopped') names the last one.

The picture of a failure (`failure_picture`) is the frame the pick was planned on: instance masks, the accepted fits'
outlines, the TRUE part's outline (white), the chosen grasp (physics and path failures) or the closest rejected
grasp of every part (no feasible grasp), and the stage and detail as a caption.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from normpos_grasp.typing import FloatArray

#: failure stage of each pick cause of `episode.CAUSES`
STAGE_OF_CAUSE = {
    "segmentation_miss": "mask",
    "wrong_fit": "fit",
    "no_feasible_grasp": "no_feasible_grasp",
    "collision": "path",
    "physics_drop": "physics",
}
STAGES = ("mask", "fit", "no_feasible_grasp", "path", "physics")
TRUE_OUTLINE = (255, 255, 255)


@dataclass(frozen=True)
class LeftPart:
    """A part still in the bin when its scene ended: true part name, stage (one of STAGES, or 'stopped' when the
    scene ran out of picks) and detail (the rejection reason, fit reason or IoU)."""

    part: str
    stage: str
    detail: str


def dominant_reason(counts: dict[str, int]) -> str:
    """The commonest rejection reason of a planner's counts ('not_evaluated' left out; ties by name)."""
    top = sorted(((-n, r) for r, n in counts.items() if r != "not_evaluated" and n > 0))
    return top[0][1] if top else "no_candidates"


def target_rejections(plan: Any) -> dict[int, dict[str, int]]:
    """Rejection counts per target index of a plan (only infeasible evaluations)."""
    per: dict[int, Counter[str]] = {}
    for ev in plan.evaluations:
        if not ev.feasible:
            per.setdefault(int(ev.candidate.target), Counter())[ev.reason] += 1
    return {k: dict(v) for k, v in per.items()}


def left_parts(
    true_names: Sequence[str],
    true_masks: Sequence[Any],
    instances: Sequence[Any],
    fits: Sequence[Any],
    plan: Any,
    match_iou: float,
) -> list[LeftPart]:
    """Trace every true part of the last frame (names and visible masks in the same order) that is still in the bin:
    the instance covering it best, the plan's target of that instance and the target's commonest rejection."""
    from normpos_grasp.perception.change import mask_iou

    per_target = target_rejections(plan) if plan is not None else {}
    targets = list(plan.targets) if plan is not None else []
    out = []
    for name, mask in zip(true_names, true_masks, strict=True):
        ious = [mask_iou(inst.mask, mask) for inst in instances]
        k = int(np.argmax(ious)) if ious else -1
        if k < 0 or ious[k] < match_iou:
            best = "partly covered" if k >= 0 and ious[k] > 0 else "no instance"
            out.append(LeftPart(name, "mask", f"not segmented ({best})"))
            continue
        iid = instances[k].instance_id
        t = next((j for j, tg in enumerate(targets) if tg.instance_id == iid), None)
        if t is None:
            fit = next((f for f in fits if f.instance_id == iid), None)
            why = (fit.reason.split(";")[0] if fit is not None and fit.reason else "no target") or "no target"
            out.append(LeftPart(name, "fit", f"no accepted fit ({why})"))
            continue
        counts = per_target.get(t, {})
        out.append(LeftPart(name, "no_feasible_grasp", dominant_reason(counts)))
    return out


def failure_picture(
    frame: Any,
    instances: Sequence[Any],
    fits: Sequence[Any],
    true_parts: Sequence[tuple[Any, FloatArray]],
    grasps: Sequence[tuple[FloatArray, float]],
    caption: str,
) -> bytes:
    """PNG of a failure: `frame` (RGBDFrame) with instance masks, accepted fit outlines, the true parts'
    outlines (template, world_from_object) in white, the grasps ((world_from_tcp, opening m)) and a caption."""
    import cv2

    from normpos_grasp.report.overlay import OutlineItem, draw_overlay, encode_png
    from normpos_grasp.report.scene3d import palette_color

    outlines = []
    for k, fit in enumerate(fits):
        if fit.accepted:
            verts = np.asarray(fit.template.mesh.vertices, dtype=np.float64) * fit.scale
            pose = fit.frame_from_object
            verts = verts @ pose[:3, :3].T + pose[:3, 3]
            outlines.append(
                OutlineItem(verts, np.asarray(fit.template.mesh.faces), fit.template.name, palette_color(k))
            )
    for tmpl, pose in true_parts:
        verts = np.asarray(tmpl.mesh.vertices, dtype=np.float64) @ pose[:3, :3].T + pose[:3, 3]
        outlines.append(OutlineItem(verts, np.asarray(tmpl.mesh.faces), f"true {tmpl.name}", TRUE_OUTLINE))
    first = grasps[0] if grasps else (None, 0.0)
    picture = draw_overlay(frame.rgb, frame.camera, list(instances), outlines, first[0], first[1])
    for pose, opening in grasps[1:]:
        picture = draw_overlay(picture, frame.camera, grasp_world_from_tcp=pose, grasp_opening_m=opening)
    bgr = cv2.cvtColor(picture, cv2.COLOR_RGB2BGR)
    lines = [caption[i : i + 90] for i in range(0, min(len(caption), 270), 90)]
    cv2.rectangle(bgr, (0, 0), (bgr.shape[1], 8 + 18 * len(lines)), (0, 0, 0), -1)
    for n, line in enumerate(lines):
        cv2.putText(bgr, line, (6, 18 + 18 * n), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return encode_png(np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8))


def cause_rows(scenes: Sequence[Any]) -> list[dict[str, Any]]:
    """The cause table of a batch: one row per (stage, detail) with its failed picks, the parts left in bins it
    explains and the first picture of it (scene order). Sorted by picks + parts left, most first."""
    rows: dict[tuple[str, str], dict[str, Any]] = {}

    def row(stage: str, detail: str) -> dict[str, Any]:
        return rows.setdefault(
            (stage, detail), {"stage": stage, "detail": detail, "failed_picks": 0, "parts_left": 0, "picture": ""}
        )

    for s in scenes:
        for p in s.picks:
            if p.success or not p.cause:
                continue
            r = row(STAGE_OF_CAUSE.get(p.cause, p.cause), p.detail)
            r["failed_picks"] += 1
            r["picture"] = r["picture"] or p.picture
        for left in s.left:
            r = row(left.stage, left.detail)
            r["parts_left"] += 1
            if not r["picture"]:
                last = s.picks[-1] if s.picks else None
                r["picture"] = last.picture if last is not None else ""
    order = {st: i for i, st in enumerate(STAGES)}
    return sorted(
        rows.values(),
        key=lambda r: (-(r["failed_picks"] + r["parts_left"]), order.get(r["stage"], 99), r["detail"]),
    )


def format_cause_table(rows: Sequence[dict[str, Any]]) -> str:
    """The cause table as fixed-width text lines (the console's)."""
    if not rows:
        return "failures by cause: none (every pick held, every bin cleared)"
    head = f"{'stage':<18} {'detail':<42} {'picks':>5} {'left':>5}  picture"
    lines = ["failures by cause (failed picks; parts left in bins):", head]
    for r in rows:
        counts = f"{r['failed_picks']:>5} {r['parts_left']:>5}"
        lines.append(f"{r['stage']:<18} {r['detail'][:42]:<42} {counts}  {r['picture'] or '-'}")
    return "\n".join(lines)
