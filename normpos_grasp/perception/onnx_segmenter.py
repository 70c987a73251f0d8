"""Instance segmentation with ONNX models in the YOLOv8/YOLO11-seg layout, run through onnxruntime.

Layout read (the one ultralytics exports and the bundled model shares):
    input  `images`  (1, C, H, W) float32, C = 3 (RGB / 255) or 4 (RGB / 255 + a depth channel, see
                     `DepthChannelSpec`), H and W multiples of the model stride;
    output0          (1, 4 + nc + nm, A): per anchor a box (cx, cy, w, h) in input pixels, nc class scores in
                     [0, 1] (already sigmoid), nm mask coefficients;
    output1          (1, nm, H / 4, W / 4): mask prototypes.
Decoding: letterbox -> confidence threshold -> class-wise NMS -> sigmoid(coefficients @ prototypes) -> remove the
letterbox padding -> resize to the frame -> threshold -> crop to the box.

Class names come from, in order: the `class_names` argument, a side file `<model>.names.json` (a JSON list or
{"names": [...]}), the model metadata key `names` (ultralytics writes a Python dict literal, JSON lists work too).
"""

from __future__ import annotations

import ast
import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.errors import InputError, ModelFormatError
from normpos_grasp.perception.mask_refine import MaskRefineOptions, SoftMask, refine_masks
from normpos_grasp.records.instance import Instance
from normpos_grasp.typing import Float32Array, FloatArray, UInt8Array

logger = logging.getLogger(__name__)

BUNDLED_MODEL = Path(__file__).resolve().parents[1] / "models" / "normpos_seg.onnx"
PAD_VALUE = 114  # letterbox grey, as ultralytics
DEPTH_METADATA_KEY = "normpos_depth"
CONF_METADATA_KEY = "normpos_conf_threshold"  # the model's recommended threshold, used when no options are given
#: class names a head refit taught the model (`training.head_tune`): weak hints, the whole library competes for them
WEAK_LABELS_METADATA_KEY = "normpos_weak_labels"


@dataclass(frozen=True)
class OnnxSegmenterOptions:
    """Decoder settings.

    Attributes:
        conf_threshold: minimum class score in [0, 1] for a detection.
        iou_threshold: box IoU above which a lower-scoring detection of the same class is suppressed.
        mask_threshold: mask probability threshold in (0, 1).
        max_detections: at most this many instances per frame (highest scores first).
        min_mask_pixels: instances with fewer mask pixels (frame resolution) are dropped.
        num_threads: onnxruntime intra-op threads.
        input_size: (H, W) for models with dynamic input size; ignored for static models.
        refine_masks: snap masks to depth steps at full resolution and resolve overlaps (`mask_refine`); applies
            to RGB-D (4-channel) models only, a no-op for RGB models.
        refine: settings of the refinement.
    """

    conf_threshold: float = 0.25
    iou_threshold: float = 0.5
    mask_threshold: float = 0.5
    max_detections: int = 100
    min_mask_pixels: int = 0
    num_threads: int = 2
    input_size: tuple[int, int] = (640, 640)
    refine_masks: bool = True
    refine: MaskRefineOptions = MaskRefineOptions()

    def __post_init__(self) -> None:
        if not 0.0 <= self.conf_threshold <= 1.0 or not 0.0 < self.iou_threshold <= 1.0:
            raise InputError(f"thresholds must lie in [0, 1], got {self.conf_threshold}, {self.iou_threshold}")
        if not 0.0 < self.mask_threshold < 1.0:
            raise InputError(f"mask_threshold must lie in (0, 1), got {self.mask_threshold}")
        if self.max_detections < 1 or self.num_threads < 1:
            raise InputError("max_detections and num_threads must be >= 1")


@dataclass(frozen=True)
class DepthChannelSpec:
    """How the 4th input channel is made from depth (stored as JSON under metadata key 'normpos_depth').

    channel = clip((reference - depth) / scale_m, -clip, clip) on valid pixels, 0 on invalid ones, where
    reference is the median valid depth of the frame (mode 'relative_median'), so the channel reads height above
    the dominant surface in units of scale_m (metres) and does not depend on the camera's distance.
    """

    mode: str = "relative_median"
    scale_m: float = 0.05
    clip: float = 4.0

    @classmethod
    def from_json(cls, text: str) -> DepthChannelSpec:
        try:
            data = json.loads(text)
            spec = cls(mode=str(data["mode"]), scale_m=float(data["scale_m"]), clip=float(data["clip"]))
        except (ValueError, KeyError, TypeError) as exc:
            raise ModelFormatError(f"metadata '{DEPTH_METADATA_KEY}' is not a valid depth spec: {text!r}") from exc
        if spec.mode != "relative_median" or spec.scale_m <= 0 or spec.clip <= 0:
            raise ModelFormatError(f"unsupported depth spec {spec}; expected mode 'relative_median', positive scale")
        return spec

    def to_json(self) -> str:
        return json.dumps({"mode": self.mode, "scale_m": self.scale_m, "clip": self.clip})


@dataclass(frozen=True)
class Letterbox:
    """Geometry of a letterbox: input = pad(resize(image, scale)); `left`, `top` padding in input pixels."""

    scale: float
    left: int
    top: int
    new_w: int
    new_h: int


def letterbox_geometry(image_hw: tuple[int, int], input_hw: tuple[int, int]) -> Letterbox:
    """Scale keeping the aspect ratio and centre with padding, rounding as ultralytics' LetterBox does."""
    h, w = image_hw
    ih, iw = input_hw
    r = min(ih / h, iw / w)
    new_w, new_h = int(round(w * r)), int(round(h * r))
    dw, dh = (iw - new_w) / 2.0, (ih - new_h) / 2.0
    return Letterbox(scale=r, left=int(round(dw - 0.1)), top=int(round(dh - 0.1)), new_w=new_w, new_h=new_h)


def depth_channel(depth_m: np.ndarray, spec: DepthChannelSpec) -> Float32Array:
    """(H, W) float32 depth channel as described by `spec`; zeros where depth is invalid (0, NaN, inf)."""
    d = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(d) & (d > 0)
    out = np.zeros(d.shape, dtype=np.float32)
    if not valid.any():
        return out
    ref = np.median(d[valid][:: max(1, int(valid.sum()) // 20000)])
    out[valid] = np.clip((ref - d[valid]) / spec.scale_m, -spec.clip, spec.clip)
    return out


def preprocess(
    rgb: UInt8Array,
    depth_m: FloatArray | None,
    input_hw: tuple[int, int],
    depth_spec: DepthChannelSpec | None,
) -> tuple[Float32Array, Letterbox]:
    """Letterbox an RGB(-D) image into the (1, C, H, W) float32 model input; C = 3 without a depth spec, else 4.

    RGB is resized bilinearly and padded with grey 114, then divided by 255; the depth channel is resized with
    nearest neighbour (no mixing across object borders) and padded with 0.
    """
    lb = letterbox_geometry(rgb.shape[:2], input_hw)
    ih, iw = input_hw
    channels = 3 if depth_spec is None else 4
    out = np.empty((1, channels, ih, iw), dtype=np.float32)
    img = (
        rgb
        if (lb.new_w, lb.new_h) == (rgb.shape[1], rgb.shape[0])
        else cv2.resize(rgb, (lb.new_w, lb.new_h), interpolation=cv2.INTER_LINEAR)
    )
    bottom, right = ih - lb.new_h - lb.top, iw - lb.new_w - lb.left
    img = cv2.copyMakeBorder(img, lb.top, bottom, lb.left, right, cv2.BORDER_CONSTANT, value=(PAD_VALUE,) * 3)
    out[0, :3] = img.transpose(2, 0, 1).astype(np.float32) * np.float32(1.0 / 255.0)
    if depth_spec is not None:
        if depth_m is None:
            raise InputError("this model needs a depth image (4 input channels), got none")
        # nearest-neighbour resampling commutes with the per-pixel channel transform, so resample first (cheaper)
        d_small = cv2.resize(np.asarray(depth_m, np.float32), (lb.new_w, lb.new_h), interpolation=cv2.INTER_NEAREST)
        dc_small = depth_channel(d_small, depth_spec)
        out[0, 3] = cv2.copyMakeBorder(dc_small, lb.top, bottom, lb.left, right, cv2.BORDER_CONSTANT, value=0.0)
    return out, lb


def nms_classwise(boxes: FloatArray, scores: FloatArray, classes: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy NMS per class. boxes (N, 4) xyxy, scores (N,), classes (N,) int -> kept indices, best first."""
    if len(boxes) == 0:
        return np.zeros(0, dtype=np.int64)
    offset = classes.astype(np.float64)[:, None] * (float(np.abs(boxes).max()) + 1.0) * 2.0
    b = boxes + offset
    x1, y1, x2, y2 = b[:, 0], b[:, 1], b[:, 2], b[:, 3]
    areas = np.maximum(x2 - x1, 0) * np.maximum(y2 - y1, 0)
    order = np.argsort(-scores, kind="stable")
    keep: list[int] = []
    while order.size:
        i = int(order[0])
        keep.append(i)
        rest = order[1:]
        iw = np.maximum(np.minimum(x2[i], x2[rest]) - np.maximum(x1[i], x1[rest]), 0)
        ih = np.maximum(np.minimum(y2[i], y2[rest]) - np.maximum(y1[i], y1[rest]), 0)
        inter = iw * ih
        iou = inter / np.maximum(areas[i] + areas[rest] - inter, 1e-12)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


@dataclass(frozen=True)
class Detections:
    """Decoded detections in frame pixels: boxes (N, 4) xyxy float64, scores (N,), classes (N,) int64,
    masks (N, H, W) bool (thresholded, cropped to the box); soft: N soft masks on windows around the boxes where
    asked for (`decode(soft_margin_px=...)`), else empty."""

    boxes: FloatArray
    scores: FloatArray
    classes: np.ndarray
    masks: np.ndarray
    soft: tuple[SoftMask, ...] = ()


def decode(
    output0: np.ndarray,
    protos: np.ndarray,
    lb: Letterbox,
    input_hw: tuple[int, int],
    image_hw: tuple[int, int],
    options: OnnxSegmenterOptions,
    soft_margin_px: int | None = None,
) -> Detections:
    """Decode the raw outputs (1, 4 + nc + nm, A) and (1, nm, mh, mw) into frame-size detections; with
    `soft_margin_px` also the soft (probability) masks on each box grown by that many pixels (`Detections.soft`)."""
    nm, mh, mw = protos.shape[1:]
    pred = output0[0]
    nc = pred.shape[0] - 4 - nm
    h0, w0 = image_hw
    empty = Detections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, h0, w0), bool))
    cls_scores = pred[4 : 4 + nc]
    classes = np.argmax(cls_scores, axis=0)
    conf = cls_scores[classes, np.arange(pred.shape[1])]
    sel = np.flatnonzero(conf > options.conf_threshold)
    if sel.size == 0:
        return empty
    xywh = pred[:4, sel].T.astype(np.float64)
    boxes = np.concatenate([xywh[:, :2] - xywh[:, 2:] / 2, xywh[:, :2] + xywh[:, 2:] / 2], axis=1)
    scores = conf[sel].astype(np.float64)
    cls = classes[sel].astype(np.int64)
    keep = nms_classwise(boxes, scores, cls, options.iou_threshold)[: options.max_detections]
    boxes, scores, cls = boxes[keep], scores[keep], cls[keep]
    coeffs = pred[4 + nc :, sel[keep]].T.astype(np.float32)  # (k, nm)
    # einsum, not BLAS: a (k, 32) x (32, n) product is too small for BLAS threads, which stall on a loaded CPU
    logits = np.einsum("kc,cn->kn", coeffs, protos[0].reshape(nm, -1).astype(np.float32))
    prob = (1.0 / (1.0 + np.exp(-np.clip(logits, -60.0, 60.0)))).reshape(-1, mh, mw)
    # remove the letterbox padding at prototype resolution, then resize to the frame
    ih, iw = input_hw
    sy, sx = mh / ih, mw / iw
    top, left = int(round(lb.top * sy - 0.1)), int(round(lb.left * sx - 0.1))
    bottom, right = int(round((lb.top + lb.new_h) * sy + 0.1)), int(round((lb.left + lb.new_w) * sx + 0.1))
    prob = prob[:, top:bottom, left:right]
    # boxes to frame pixels
    boxes = (boxes - np.array([lb.left, lb.top, lb.left, lb.top], dtype=np.float64)) / lb.scale
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, w0)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, h0)
    # each mask: the bilinear resize of the (unpadded) prototype mask to the frame, evaluated only inside its box
    # (cv2.resize's pixel-centre mapping, computed for the box window with warpAffine), then thresholded
    masks = np.zeros((len(keep), h0, w0), dtype=bool)
    soft: list[SoftMask] = []
    ph, pw = prob.shape[1:]
    ax, ay = pw / w0, ph / h0
    margin = -1 if soft_margin_px is None else int(soft_margin_px)
    for k, (x1, y1, x2, y2) in enumerate(boxes):
        xa, ya = int(np.floor(x1)), int(np.floor(y1))
        xb, yb = int(np.ceil(x2)), int(np.ceil(y2))
        if xb <= xa or yb <= ya:
            if margin >= 0:
                soft.append(SoftMask(np.zeros((0, 0), np.float32), xa, ya))
            continue
        if margin >= 0:  # the soft window around the box; the box mask is its thresholded centre part
            xs, ys = max(xa - margin, 0), max(ya - margin, 0)
            xe, ye = min(xb + margin, w0), min(yb + margin, h0)
        else:
            xs, ys, xe, ye = xa, ya, xb, yb
        m = np.array([[ax, 0.0, (xs + 0.5) * ax - 0.5], [0.0, ay, (ys + 0.5) * ay - 0.5]])
        win = cv2.warpAffine(
            np.ascontiguousarray(prob[k]),
            m,
            (xe - xs, ye - ys),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )
        masks[k, ya:yb, xa:xb] = win[ya - ys : yb - ys, xa - xs : xb - xs] > options.mask_threshold
        if margin >= 0:
            soft.append(SoftMask(np.asarray(win, dtype=np.float32), xs, ys))
    return Detections(boxes=boxes, scores=scores, classes=cls, masks=masks, soft=tuple(soft))


def _parse_names(text: str) -> list[str]:
    try:
        data: Any = json.loads(text)
    except ValueError:
        try:
            data = ast.literal_eval(text)
        except (ValueError, SyntaxError) as exc:
            raise ModelFormatError(f"class names metadata is neither JSON nor a Python literal: {text[:80]!r}") from exc
    if isinstance(data, dict) and "names" in data:
        data = data["names"]
    if isinstance(data, dict):
        try:
            return [str(data[k]) for k in sorted(data, key=int)]
        except (ValueError, TypeError) as exc:
            raise ModelFormatError(f"class names dict must have integer keys, got {list(data)[:5]}") from exc
    if isinstance(data, list):
        return [str(x) for x in data]
    raise ModelFormatError(f"class names must be a list or an index->name dict, got {type(data).__name__}")


class OnnxSegmenter:
    """A `Segmenter` running a YOLOv8/YOLO11-seg-layout ONNX model (see module docstring).

    Args:
        model_path: the .onnx file; None loads the bundled model trained on this project's synthetic scenes.
        class_names: overrides the names from the side file or metadata; must have nc entries.
        options: decoder settings; None: defaults, with the confidence threshold the model recommends in its
            metadata (key 'normpos_conf_threshold') where it has one.
    """

    def __init__(
        self,
        model_path: str | Path | None = None,
        class_names: Sequence[str] | None = None,
        options: OnnxSegmenterOptions | None = None,
    ) -> None:
        import onnxruntime as ort

        self.options = options or OnnxSegmenterOptions()
        self.model_path = Path(model_path) if model_path is not None else BUNDLED_MODEL
        if not self.model_path.is_file():
            raise ModelFormatError(f"ONNX model not found: {self.model_path}")
        so = ort.SessionOptions()
        so.intra_op_num_threads = self.options.num_threads
        so.inter_op_num_threads = 1
        so.log_severity_level = 3
        # no busy-waiting of the worker threads after a run: they would burn a core beside the decoding and mask
        # refinement that follow (and beside other processes on a shared CPU)
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self._session = ort.InferenceSession(str(self.model_path), so, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for unreadable models
            raise ModelFormatError(f"onnxruntime cannot load {self.model_path}: {exc}") from exc
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4:
            raise ModelFormatError(
                f"expected one input (1, C, H, W), got {[(i.name, i.shape) for i in inputs]}; "
                "export the model with a single image input"
            )
        if len(outputs) < 2 or len(outputs[0].shape) != 3 or len(outputs[1].shape) != 4:
            raise ModelFormatError(
                "expected outputs output0 (1, 4 + nc + nm, anchors) and output1 prototypes (1, nm, H/4, W/4), got "
                f"{[(o.name, o.shape) for o in outputs]}; is this a detection-only (not -seg) model?"
            )
        self._input_name = inputs[0].name
        self._output_names = [outputs[0].name, outputs[1].name]
        shape = inputs[0].shape
        meta = self._session.get_modelmeta().custom_metadata_map
        channels = shape[1] if isinstance(shape[1], int) else int(meta.get("channels", 3))
        if channels not in (3, 4):
            raise ModelFormatError(f"expected 3 (RGB) or 4 (RGB-D) input channels, the model has {channels}")
        self.depth_spec: DepthChannelSpec | None = None
        if channels == 4:
            if DEPTH_METADATA_KEY not in meta:
                raise ModelFormatError(
                    f"a 4-channel model needs metadata '{DEPTH_METADATA_KEY}' describing its depth channel"
                )
            self.depth_spec = DepthChannelSpec.from_json(meta[DEPTH_METADATA_KEY])
        if isinstance(shape[2], int) and isinstance(shape[3], int):
            self.input_hw: tuple[int, int] = (shape[2], shape[3])
        else:
            self.input_hw = tuple(self.options.input_size)  # type: ignore[assignment]
        self.num_prototypes = outputs[1].shape[1] if isinstance(outputs[1].shape[1], int) else None
        nc = None
        if isinstance(outputs[0].shape[1], int) and self.num_prototypes is not None:
            nc = outputs[0].shape[1] - 4 - self.num_prototypes
            if nc < 1:
                raise ModelFormatError(f"output0 has {outputs[0].shape[1]} rows, fewer than 4 + 1 + nm")
        if options is None and CONF_METADATA_KEY in meta:
            try:
                self.options = OnnxSegmenterOptions(conf_threshold=float(meta[CONF_METADATA_KEY]))
            except ValueError as exc:
                raise ModelFormatError(
                    f"metadata '{CONF_METADATA_KEY}' is not a number: {meta[CONF_METADATA_KEY]!r}"
                ) from exc
        self.class_names = self._load_names(class_names, meta, nc)
        self.weak_labels: tuple[str, ...] = ()
        if WEAK_LABELS_METADATA_KEY in meta:
            self.weak_labels = tuple(_parse_names(meta[WEAK_LABELS_METADATA_KEY]))
        self.metadata = dict(meta)

    def _load_names(self, class_names: Sequence[str] | None, meta: dict[str, str], nc: int | None) -> list[str]:
        side = self.model_path.with_suffix(".names.json")
        if class_names is not None:
            names = [str(n) for n in class_names]
        elif side.is_file():
            names = _parse_names(side.read_text())
        elif "names" in meta:
            names = _parse_names(meta["names"])
        elif nc is not None:
            logger.warning("no class names for %s; using class_0..class_%d", self.model_path.name, nc - 1)
            names = [f"class_{i}" for i in range(nc)]
        else:
            raise ModelFormatError(f"{self.model_path} has no class names; pass class_names or add {side.name}")
        if nc is not None and len(names) != nc:
            raise ModelFormatError(f"the model has {nc} classes but {len(names)} class names were given: {names}")
        return names

    @property
    def channels(self) -> int:
        return 3 if self.depth_spec is None else 4

    def run_raw(self, rgb: UInt8Array, depth_m: FloatArray | None = None) -> tuple[np.ndarray, np.ndarray, Letterbox]:
        """Pre-process and run the model; returns (output0, output1, letterbox)."""
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise InputError(f"rgb must be (H, W, 3) uint8, got {rgb.dtype} {rgb.shape}")
        if rgb.shape[0] < 8 or rgb.shape[1] < 8:
            raise InputError(f"image of {rgb.shape[1]}x{rgb.shape[0]} px is too small to segment")
        if depth_m is not None and np.shape(depth_m) != rgb.shape[:2]:
            raise InputError(f"depth must be (H, W) = {rgb.shape[:2]}, got {np.shape(depth_m)}")
        x, lb = preprocess(rgb, depth_m, self.input_hw, self.depth_spec)
        out0, out1 = self._session.run(self._output_names, {self._input_name: x})
        nm = out1.shape[1]
        if out0.ndim != 3 or out1.ndim != 4 or out0.shape[1] - 4 - nm != len(self.class_names):
            raise ModelFormatError(
                f"outputs {out0.shape} and {out1.shape} do not match 4 + {len(self.class_names)} classes + nm"
            )
        return out0, out1, lb

    def detect(self, rgb: UInt8Array, depth_m: FloatArray | None = None) -> Detections:
        """Detections (boxes, scores, classes, masks) in frame pixels for one image."""
        out0, out1, lb = self.run_raw(rgb, depth_m)
        refine = self.options.refine_masks and self.depth_spec is not None and depth_m is not None
        margin = self.options.refine.margin_px if refine else None
        det = decode(out0, out1, lb, self.input_hw, rgb.shape[:2], self.options, soft_margin_px=margin)
        if not refine or len(det.scores) == 0:
            return det
        # refine_masks keeps a pixel only where its soft score beats every other instance's, so the overlap
        # order is by score, independent of the detection order
        masks = refine_masks(det.soft, depth_m, rgb.shape[:2], self.options.refine, rgb=rgb)
        return Detections(det.boxes, det.scores, det.classes, masks, det.soft)

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        """Instances of the frame, best score first, instance_id 1..N; [] when nothing is found."""
        if not isinstance(frame, RGBDFrame):
            raise InputError(f"expected an RGBDFrame, got {type(frame).__name__}")
        det = self.detect(frame.rgb, frame.depth_m if self.depth_spec is not None else None)
        out: list[Instance] = []
        for k in range(len(det.scores)):
            mask = det.masks[k]
            if int(mask.sum()) < max(1, self.options.min_mask_pixels):
                continue
            out.append(
                Instance(
                    mask=mask,
                    label=self.class_names[int(det.classes[k])],
                    score=float(np.clip(det.scores[k], 0.0, 1.0)),
                    instance_id=len(out) + 1,
                    source_id=int(det.classes[k]),
                )
            )
        return out
