"""The bundled segmenter taught new parts on CPU without torch: its output heads refitted on a frozen trunk.

The model (training/model.py) ends in three 1x1 convolutions on one 96-channel feature map at stride 8: class logits,
box sides (softplus x stride) and the 32 mask coefficients of each cell. Everything before them (the trunk: backbone,
pyramid, prototypes) stays as trained on 2100 frames of eight parts; the heads are refitted as k x k convolutions
(`HeadTuneOptions.kernel`, 3: a cell sees its neighbours, which a T-profile's box needs) on synthetic bins of the
library, starting from the bundled heads (the 1x1 weights as the centre tap) and pulled towards them:

- classes: the sigmoid focal loss of training (alpha 0.25, gamma 2) over the cells, all classes at once (new rows
  start at the prior 0.01; `fit_known_classes`), on every positive cell and a seeded share of the negative ones
  (weighted back);
- boxes: least squares on softplus^-1(side / stride) at the positive cells (closed form);
- mask coefficients: the box-cropped logistic loss of sigmoid(coefficients . prototypes) against the part's mask,
  each positive cell's box weighted equally.

Each is a convex problem of a few thousand weights on features computed once per frame, solved with scipy's
L-BFGS in minutes on 2 cores, where back-propagating through the whole network (the `[train]` extra, torch) took
about 150 minutes of CPU for the bundled model. The tuned weights are written into a copy of the ONNX file with the
new class names, the chosen confidence threshold and `normpos_weak_labels`: classes learned this way are weak hints
(`pipeline.perceive` lets the whole library compete for a mask that names one), since a head on a frozen trunk
tells new parts apart less surely than the trunk's own classes. Why not the whole network: torch is not in the
product's lock file, and a head refit cannot unlearn the built-in parts' features.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.atomic import atomic_write_bytes
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.errors import ModelFormatError
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.perception.onnx_segmenter import (
    CONF_METADATA_KEY,
    DEPTH_METADATA_KEY,
    WEAK_LABELS_METADATA_KEY,
    DepthChannelSpec,
)
from normpos_grasp.records.template import Template
from normpos_grasp.training.data import Sample, assign_cells, pack_sample
from normpos_grasp.typing import FloatArray

logger = logging.getLogger(__name__)

#: the feature map the heads read (the bundled model's graph)
FEATURES = "/net/head/head.2/Relu_output_0"
#: head name -> (convolution node, weight initialiser, bias initialiser)
HEADS = {
    "cls": ("/net/cls/Conv", "net.cls.weight", "net.cls.bias"),
    "box": ("/net/box/Conv", "net.box.weight", "net.box.bias"),
    "coef": ("/net/coef/Conv", "net.coef.weight", "net.coef.bias"),
}
#: metadata key of the refit's record (options, data, figures)
TUNE_KEY = "normpos_head_tune"


@dataclass(frozen=True)
class HeadTuneOptions:
    """kernel: the refitted heads' k x k window (odd). negative_share: share of the cells without a part kept for
    the class loss (seeded), weighted by its inverse. prior: pull towards the bundled heads (L2, relative).
    cls_iterations, coef_iterations: L-BFGS iterations at most. seed: the negative cells' draw. fit_known_classes:
    refit the model's own class rows too (False: only the new classes' rows; then a built-in class such as 'plate'
    keeps firing on a T-profile beside the new class: on bench_teach's bins new-part segmentation 0.50 / 0.54
    against 0.60 / 0.66)."""

    kernel: int = 3
    negative_share: float = 0.2
    prior: float = 1.0
    cls_iterations: int = 300
    coef_iterations: int = 150
    seed: int = 0
    fit_known_classes: bool = True

    def __post_init__(self) -> None:
        if self.kernel < 1 or self.kernel % 2 == 0:
            raise ValueError(f"kernel must be odd and >= 1, got {self.kernel}")
        if not 0.0 < self.negative_share <= 1.0:
            raise ValueError(f"negative_share must be in (0, 1], got {self.negative_share}")


@dataclass(frozen=True)
class Heads:
    """The three heads as (out, 96 * k * k + 1) matrices (weights in ONNX order: channel, row, column; bias last)."""

    cls: FloatArray
    box: FloatArray
    coef: FloatArray
    kernel: int


@dataclass(frozen=True, eq=False)
class FrameData:
    """One frame for the refit: features (A, D + 1) float32 (the k x k windows, 1 appended), assign (A,) part per
    cell (-1 none), boxes (n, 4) xyxy input pixels, classes (n,), masks (n, mh * mw) bool, protos (nm, mh * mw)."""

    features: np.ndarray
    assign: np.ndarray
    boxes: np.ndarray
    classes: np.ndarray
    masks: np.ndarray
    protos: np.ndarray


class Trunk:
    """The frozen network: a frame's preprocessed input -> (features (96, h, w), prototypes (nm, mh, mw)).
    Raises ModelFormatError when the model is not the bundled layout (its heads named as in `HEADS`)."""

    def __init__(self, model_path: str | Path) -> None:
        import onnx
        import onnxruntime as ort

        self.model_path = Path(model_path)
        model = onnx.load(str(self.model_path))
        nodes = {n.name for n in model.graph.node}
        inits = {i.name for i in model.graph.initializer}
        for conv, w, b in HEADS.values():
            if conv not in nodes or w not in inits or b not in inits:
                raise ModelFormatError(f"{self.model_path} is not the bundled model's layout (no {conv} with {w})")
        model.graph.output.append(onnx.helper.make_tensor_value_info(FEATURES, onnx.TensorProto.FLOAT, None))
        self.meta = {p.key: p.value for p in model.metadata_props}
        self.names: list[str] = json.loads(self.meta.get("names", "[]"))
        self.spec = DepthChannelSpec.from_json(self.meta[DEPTH_METADATA_KEY])
        ih, iw = (int(v) for v in json.loads(self.meta.get("imgsz", "[192, 256]")))
        self.input_hw = (ih, iw)
        self.stride = int(self.meta.get("stride", "8"))
        so = ort.SessionOptions()
        so.intra_op_num_threads = 1
        self._session = ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])
        self._input = self._session.get_inputs()[0].name
        self.base = self._base_heads(model)

    @staticmethod
    def _base_heads(model: Any) -> Heads:
        from onnx import numpy_helper

        w = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
        mats = {}
        for key, (_, wn, bn) in HEADS.items():
            weight, bias = w[wn], w[bn]
            if weight.shape[2:] != (1, 1):
                raise ModelFormatError(
                    f"head {key} is {weight.shape[2]}x{weight.shape[3]}, not 1x1: refit the bundled model"
                )
            mats[key] = np.c_[weight[:, :, 0, 0], bias].astype(np.float64)
        return Heads(mats["cls"], mats["box"], mats["coef"], 1)

    def run(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(features (C, h, w), prototypes (nm, mh, mw)) of one input (1, 4, H, W)."""
        _, protos, feats = self._session.run(None, {self._input: x.astype(np.float32)})
        return feats[0], protos[0]


def windows(features: np.ndarray, kernel: int) -> np.ndarray:
    """(h * w, C * k * k + 1) float32: each cell's k x k window (zero padded; channel, row, column order), 1 last."""
    c, h, w = features.shape
    r = kernel // 2
    padded = np.pad(features, ((0, 0), (r, r), (r, r)))
    taps = np.stack([padded[:, dy : dy + h, dx : dx + w] for dy in range(kernel) for dx in range(kernel)], axis=1)
    flat = taps.reshape(c * kernel * kernel, h * w).T
    return np.ascontiguousarray(np.c_[flat, np.ones(h * w)], dtype=np.float32)


def lift(heads: Heads, kernel: int) -> Heads:
    """1x1 heads as k x k ones: the weights on the centre tap, zeros around it (the same outputs)."""
    if heads.kernel == kernel:
        return heads
    if heads.kernel != 1:
        raise ValueError("only 1x1 heads can be lifted")

    def one(m: FloatArray) -> FloatArray:
        c = m.shape[1] - 1
        out = np.zeros((len(m), c * kernel * kernel + 1))
        out[:, np.arange(c) * kernel * kernel + (kernel * kernel) // 2] = m[:, :c]
        out[:, -1] = m[:, -1]
        return out

    return Heads(one(heads.cls), one(heads.box), one(heads.coef), kernel)


def frame_data(sample: Sample, trunk: Trunk, class_names: Sequence[str], kernel: int) -> FrameData:
    """The refit's view of one frame: its features, the cells each part teaches and the part's box and mask."""
    x, masks, boxes, classes = pack_sample(sample, trunk.input_hw, trunk.spec, class_names=class_names)
    feats, protos = trunk.run(x[None])
    h, w = feats.shape[1:]
    ys, xs = np.mgrid[0:h, 0:w]
    centres = np.c_[(xs.ravel() + 0.5) * trunk.stride, (ys.ravel() + 0.5) * trunk.stride]
    assign = assign_cells(boxes, masks, centres, trunk.stride)
    return FrameData(
        windows(feats, kernel),
        assign,
        boxes.astype(np.float64),
        classes,
        masks.reshape(len(masks), -1),
        protos.reshape(len(protos), -1).astype(np.float64),
    )


#: share of the fit's time the class head gets (the mask coefficients get the rest); of `tune_segmenter`'s budget,
#: the rendering gets RENDER_SHARE and the fits until FIT_END (validation after it)
CLS_SHARE = 0.5
RENDER_SHARE = 0.3
FIT_END = 0.9


def _stopper(deadline: float) -> Callable[[object], None]:
    def stop(_: object) -> None:
        if time.perf_counter() > deadline:
            raise StopIteration

    return stop


def fit_heads(
    frames: Sequence[FrameData],
    base: Heads,
    n_classes: int,
    input_hw: tuple[int, int],
    stride: int,
    options: HeadTuneOptions = HeadTuneOptions(),
    deadline: float = float("inf"),
) -> Heads:
    """The heads refitted on `frames` (see the module docstring), from `base` (lifted to the kernel) with rows for
    `n_classes` classes (new ones at the prior 0.01). `deadline` (perf_counter s) cuts the L-BFGS runs short: the
    class fit gets `CLS_SHARE` of the time left, the mask coefficients the rest (a class fit that took it all left
    the bundled mask head on the new parts: worse masks, wrong poses accepted on them)."""
    from scipy.optimize import minimize

    start = lift(base, options.kernel)
    cls0 = np.zeros((n_classes, start.cls.shape[1]))
    cls0[: len(start.cls)] = start.cls
    cls0[len(start.cls) :, -1] = -4.6
    h, w = input_hw[0] // stride, input_hw[1] // stride
    ys, xs = np.mgrid[0:h, 0:w]
    centres = np.c_[(xs.ravel() + 0.5) * stride, (ys.ravel() + 0.5) * stride]
    rng = np.random.default_rng(options.seed)

    # classes: focal loss over the positive cells and a share of the negative ones
    rows, targets, weights = [], [], []
    for f in frames:
        pos = f.assign >= 0
        keep = np.flatnonzero(pos | (rng.random(len(pos)) < options.negative_share))
        rows.append(f.features[keep])
        y = np.zeros((len(keep), n_classes))
        kp = f.assign[keep] >= 0
        y[np.flatnonzero(kp), f.classes[f.assign[keep][kp]]] = 1.0
        targets.append(y)
        weights.append(np.where(kp, 1.0, 1.0 / options.negative_share))
    feats, y, cw = np.concatenate(rows).astype(np.float64), np.concatenate(targets), np.concatenate(weights)[:, None]
    n_pos = max(float(y.sum()), 1.0)
    lam = options.prior * 1e-3
    alpha, gamma = 0.25, 2.0

    fit = slice(0 if options.fit_known_classes else len(start.cls), n_classes)  # the rows refitted
    w0, y = cls0[fit], y[:, fit]

    def cls_loss(v: FloatArray) -> tuple[float, FloatArray]:
        wm = v.reshape(w0.shape)
        p = 1.0 / (1.0 + np.exp(-np.clip(feats @ wm.T, -40, 40)))
        pt = np.clip(np.where(y > 0, p, 1 - p), 1e-12, 1.0)
        at = np.where(y > 0, alpha, 1 - alpha)
        log_pt = np.log(pt)
        loss = -(cw * at * (1 - pt) ** gamma * log_pt).sum()
        d_pt = -at * (-gamma * (1 - pt) ** (gamma - 1) * log_pt + (1 - pt) ** gamma / pt)
        d_z = cw * d_pt * np.where(y > 0, 1.0, -1.0) * p * (1 - p)
        r = wm - w0
        return float(loss / n_pos + lam * (r**2).sum()), ((d_z.T @ feats) / n_pos + 2 * lam * r).ravel()

    now = time.perf_counter()
    stop = _stopper(now + CLS_SHARE * (deadline - now) if np.isfinite(deadline) else deadline)
    res = minimize(cls_loss, w0.ravel(), jac=True, method="L-BFGS-B", callback=stop,
                   options={"maxiter": options.cls_iterations})  # fmt: skip
    cls = cls0.copy()
    cls[fit] = res.x.reshape(w0.shape)

    # boxes: least squares on softplus^-1(side / stride) at the positive cells, pulled towards the start
    pos_rows, sides = [], []
    for f in frames:
        cells = np.flatnonzero(f.assign >= 0)
        if not len(cells):
            continue
        b, c = f.boxes[f.assign[cells]], centres[cells]
        d = np.c_[c[:, 0] - b[:, 0], c[:, 1] - b[:, 1], b[:, 2] - c[:, 0], b[:, 3] - c[:, 1]] / stride
        d = np.clip(d, 0.05, None)
        sides.append(np.where(d > 20, d, np.log(np.expm1(np.minimum(d, 20)))))
        pos_rows.append(f.features[cells].astype(np.float64))
    if not pos_rows:
        return Heads(cls, start.box, start.coef, options.kernel)
    hp, z = np.concatenate(pos_rows), np.concatenate(sides)
    ridge = options.prior * 1e-3 * len(hp)
    box = np.linalg.solve(hp.T @ hp + ridge * np.eye(hp.shape[1]), hp.T @ z + ridge * start.box.T).T

    # mask coefficients: box-cropped logistic loss against each positive cell's part mask
    mh, mw = input_hw[0] // 4, input_hw[1] // 4
    px = np.tile((np.arange(mw) + 0.5) * 4, mh)
    py = np.repeat((np.arange(mh) + 0.5) * 4, mw)
    cell_rows, protos, labels, owner = [], [], [], []
    k = 0
    for f in frames:
        for cell in np.flatnonzero(f.assign >= 0):
            g = f.assign[cell]
            x1, y1, x2, y2 = f.boxes[g]
            inside = np.flatnonzero((px >= x1) & (px <= x2) & (py >= y1) & (py <= y2))
            if not len(inside):
                continue
            cell_rows.append(f.features[cell])
            protos.append(f.protos[:, inside].T)
            labels.append(f.masks[g, inside].astype(np.float64))
            owner.append(np.full(len(inside), k))
            k += 1
    if not k:
        return Heads(cls, box, start.coef, options.kernel)
    hc = np.asarray(cell_rows, np.float64)
    pc, mc, own = np.concatenate(protos), np.concatenate(labels), np.concatenate(owner)
    per = 1.0 / np.bincount(own)[own] / k
    starts = np.r_[0, np.flatnonzero(np.diff(own)) + 1]
    lam_c = options.prior * 1e-4

    def coef_loss(v: FloatArray) -> tuple[float, FloatArray]:
        wm = v.reshape(start.coef.shape)
        c = hc @ wm.T
        zz = np.clip(np.einsum("pk,pk->p", pc, c[own]), -40, 40)
        loss = (per * (np.logaddexp(0, zz) - mc * zz)).sum()
        dz = per * (1.0 / (1.0 + np.exp(-zz)) - mc)
        dc = np.add.reduceat(dz[:, None] * pc, starts, axis=0)  # per cell (owners are consecutive)
        r = wm - start.coef
        return float(loss + lam_c * (r**2).sum()), (dc.T @ hc + 2 * lam_c * r).ravel()

    stop = _stopper(deadline)
    res = minimize(coef_loss, start.coef.ravel(), jac=True, method="L-BFGS-B", callback=stop,
                   options={"maxiter": options.coef_iterations})  # fmt: skip
    return Heads(cls, box, res.x.reshape(start.coef.shape), options.kernel)


def write_model(
    base_path: str | Path,
    heads: Heads,
    class_names: Sequence[str],
    weak_labels: Sequence[str],
    conf_threshold: float,
    out_path: str | Path,
    record: dict[str, object],
) -> Path:
    """A copy of the model at `base_path` with `heads` as its k x k head convolutions, `class_names` (metadata
    `names`), `weak_labels`, `conf_threshold` and `record` (JSON) in its metadata; written atomically."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(base_path))
    k = heads.kernel
    mats = {"cls": heads.cls, "box": heads.box, "coef": heads.coef}
    for key, (conv, wn, bn) in HEADS.items():
        m = mats[key]
        arrays = {wn: m[:, :-1].reshape(len(m), -1, k, k), bn: m[:, -1]}
        for i, init in enumerate(model.graph.initializer):
            if init.name in arrays:
                tensor = numpy_helper.from_array(arrays[init.name].astype(np.float32), init.name)
                model.graph.initializer[i].CopyFrom(tensor)
        for node in model.graph.node:
            if node.name == conv:
                for a in node.attribute:
                    if a.name == "kernel_shape":
                        a.ints[:] = [k, k]
                    elif a.name == "pads":
                        a.ints[:] = [k // 2] * 4
    out0 = model.graph.output[0].type.tensor_type.shape.dim
    out0[1].dim_value = 4 + len(class_names) + len(heads.coef)
    meta = {p.key: p for p in model.metadata_props}
    values = {
        "names": json.dumps(list(class_names)),
        CONF_METADATA_KEY: f"{conf_threshold:.2f}",
        WEAK_LABELS_METADATA_KEY: json.dumps(list(weak_labels)),
        TUNE_KEY: json.dumps(record, sort_keys=True),
    }
    for key, value in values.items():
        prop = meta[key] if key in meta else model.metadata_props.add()
        prop.key, prop.value = key, value
    onnx.checker.check_model(model)
    out = Path(out_path)
    atomic_write_bytes(out, model.SerializeToString())
    return out


def tune_record(options: HeadTuneOptions, **facts: object) -> dict[str, object]:
    """The record stored with a tuned model: the options and the given facts (data, timings, figures)."""
    return {"options": asdict(options), **facts}


@dataclass(frozen=True)
class TuneReport:
    """What `tune_segmenter` made: the model, its classes (new_labels learned here), the frames it saw, the chosen
    confidence threshold, validation figures on held-back seeds ('new' and 'built-in' parts, the tuned model and
    the base model: recall, precision and mask IoU at IoU 0.5, with the class), and timings (s)."""

    model_path: Path
    class_names: tuple[str, ...]
    new_labels: tuple[str, ...]
    frames: int
    val_frames: int
    conf_threshold: float
    figures: dict[str, dict[str, float]]
    timings_s: dict[str, float]


#: confidence thresholds tried on the validation frames
THRESHOLDS = (0.25, 0.3, 0.35, 0.4, 0.45, 0.5)


def _figures(segmenter: Segmenter, samples: Sequence[Sample], new: set[str]) -> dict[str, dict[str, float]]:
    """Recall / precision / mean IoU per group ('new', 'built-in'): predictions labelled in the group matched to
    the group's true instances (the class must be right); 'new (any class)': every prediction against the new parts
    (what a class-agnostic use of the model finds)."""
    from normpos_grasp.training.metrics import MatchStats

    stats = {"new": MatchStats(), "built-in": MatchStats(), "new (any class)": MatchStats()}
    for s in samples:
        pred = segmenter.segment(s.frame)
        for group, inside in (("new", True), ("built-in", False)):
            gt = [(g, v) for g, v in zip(s.instances, s.visib_fract, strict=True) if (g.label in new) == inside]
            mine = [p for p in pred if (p.label in new) == inside]
            stats[group].add(mine, [g for g, _ in gt], np.array([v for _, v in gt]))
            if inside:
                stats["new (any class)"].add(pred, [g for g, _ in gt], np.array([v for _, v in gt]))
    return {
        k: {"recall": v.recall, "precision": v.precision, "mean_iou": v.mean_iou, "gt": float(v.gt)}
        for k, v in stats.items()
    }


def tune_segmenter(
    templates: Sequence[Template],
    out_dir: str | Path,
    cell: CellConfig,
    scenes: int = 300,
    val_scenes: int = 20,
    first_seed: int = 500000,
    val_first_seed: int = 560000,
    budget_s: float = 600.0,
    base_model: str | Path | None = None,
    options: HeadTuneOptions = HeadTuneOptions(),
    log: Callable[[str], None] = logger.info,
) -> TuneReport:
    """Teach the model at `base_model` (default: the bundled one) the labels of `templates` it lacks: render
    `scenes` bins of `cell` (two views each: full, then some parts taken out) with the new parts about half of the
    draws and the library's other parts the rest, refit its heads (`fit_heads`) within `budget_s` (rendering
    stops at `RENDER_SHARE` of it, the fits at `FIT_END`), choose the confidence threshold with the best mean F1 of
    new and built-in parts on `val_scenes` held-back bins (seeds from `val_first_seed`), and write
    OUT/normpos_seg.onnx and its model card OUT/MODEL_CARD.md. Raises InputError when the model already knows every
    label."""
    from normpos_grasp.errors import InputError
    from normpos_grasp.perception.onnx_segmenter import BUNDLED_MODEL, OnnxSegmenter, OnnxSegmenterOptions
    from normpos_grasp.training.data import cell_samples

    t_start = time.perf_counter()
    base_path = Path(base_model) if base_model is not None else BUNDLED_MODEL
    trunk = Trunk(base_path)
    labels = list(dict.fromkeys(str(t.label) for t in templates))
    new = [lb for lb in labels if lb and lb not in trunk.names]
    if not new:
        raise InputError(f"the model already knows every label of the library ({', '.join(labels)}): nothing to teach")
    names = [*trunk.names, *new]
    unknown = sorted(lb for lb in labels if lb not in names)
    if unknown:
        raise InputError(f"labels {unknown} are neither the model's nor the library's")
    by_label = {str(t.label): str(t.name) for t in templates}
    others = [str(t.name) for t in templates if str(t.label) not in new]
    draw = tuple([by_label[lb] for lb in new] * max(1, len(others) // len(new)) + others)
    library = list(templates)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    frames: list[FrameData] = []
    render_until = t_start + RENDER_SHARE * budget_s
    done = 0
    for seed in range(first_seed, first_seed + scenes):
        if time.perf_counter() > render_until and frames:
            log(f"rendering stopped by the budget after {done} of {scenes} scenes")
            break
        for s in cell_samples(cell, seed, library=library, parts=draw):
            frames.append(frame_data(s, trunk, names, options.kernel))
        done += 1
    t_render = time.perf_counter() - t_start
    val_seeds = range(val_first_seed, val_first_seed + val_scenes)
    val = [s for seed in val_seeds for s in cell_samples(cell, seed, library=library, parts=draw)]
    log(f"{len(frames)} frames of {done} scenes rendered in {t_render:.0f} s; {len(val)} validation frames")
    t0 = time.perf_counter()
    heads = fit_heads(
        frames, trunk.base, len(names), trunk.input_hw, trunk.stride, options, t_start + FIT_END * budget_s
    )  # fmt: skip
    t_fit = time.perf_counter() - t0
    log(f"heads refitted in {t_fit:.0f} s")
    model_path = out / "normpos_seg.onnx"
    record = tune_record(options, base=base_path.name, new_labels=new, scenes=done, frames=len(frames),
                         first_seed=first_seed, val_first_seed=val_first_seed, val_frames=len(val))  # fmt: skip
    write_model(base_path, heads, names, new, 0.35, model_path, record)
    t0 = time.perf_counter()
    best: tuple[float, float, dict[str, dict[str, float]]] = (-1.0, 0.35, {})
    for thr in THRESHOLDS:
        figs = _figures(OnnxSegmenter(model_path, options=OnnxSegmenterOptions(conf_threshold=thr)), val, set(new))
        f1 = [2 * f["recall"] * f["precision"] / max(f["recall"] + f["precision"], 1e-9)
              for k, f in figs.items() if k in ("new", "built-in")]  # fmt: skip
        if float(np.mean(f1)) > best[0]:
            best = (float(np.mean(f1)), thr, figs)
    base_figs = _figures(OnnxSegmenter(base_path), val, set(new))
    figures = {f"tuned {k}": v for k, v in best[2].items()} | {f"base {k}": v for k, v in base_figs.items()}
    t_val = time.perf_counter() - t0
    timings = {"render": t_render, "fit": t_fit, "validate": t_val, "total": time.perf_counter() - t_start}
    record = {**record, "conf_threshold": best[1], "figures": figures, "timings_s": timings}
    write_model(base_path, heads, names, new, best[1], model_path, record)
    report = TuneReport(model_path, tuple(names), tuple(new), len(frames), len(val), best[1], figures, timings)
    from normpos_grasp.atomic import atomic_write_text

    atomic_write_text(out / "MODEL_CARD.md", model_card(report, options))
    return report


def model_card(report: TuneReport, options: HeadTuneOptions) -> str:
    """The tuned model's card (Markdown): classes, data, method, threshold, validation figures, timings."""
    lines = [
        f"# {report.model_path.name}: the bundled segmenter taught {', '.join(report.new_labels)}",
        "",
        "| | |",
        "|---|---|",
        f"| classes | {', '.join(report.class_names)} (learned here, weak hints: {', '.join(report.new_labels)}) |",
        f"| data | {report.frames} synthetic frames (bins of the cell, D435 noise), {report.val_frames} held back |",
        f"| method | heads refitted as {options.kernel}x{options.kernel} convs on the frozen trunk (head_tune) |",
        f"| threshold | {report.conf_threshold:.2f} (best mean F1 of new and built-in parts on the held-back frames) |",
        "| timings | " + ", ".join(f"{k} {v:.0f} s" for k, v in report.timings_s.items()) + " |",
        "",
        "| validation (IoU 0.5) | true instances | recall | precision | mask IoU |",
        "|---|---|---|---|---|",
    ]
    for k, f in report.figures.items():
        lines.append(f"| {k} | {f['gt']:.0f} | {f['recall']:.3f} | {f['precision']:.3f} | {f['mean_iou']:.3f} |")
    return "\n".join(lines) + "\n"
