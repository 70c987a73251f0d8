"""Training of the bundled segmentation model and its ONNX export (needs torch: the `train` extra).

Data: shards written by `generate_shards` (synthetic scenes, D435 noise, seeds given). Targets: anchor-free
centre sampling: a stride-8 cell is positive for a part when its centre lies inside the part's visible mask
and near the box centre (the smallest part wins); every part gets at least its cell nearest the mask centroid.
Losses: sigmoid focal loss (classes), GIoU (boxes), box-cropped BCE of sigmoid(coefficients . prototypes)
against the visible mask (YOLACT). Reproducible: the seed fixes the data order, augmentation and initial
weights; torch runs deterministic CPU kernels with a fixed thread count.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from normpos_grasp.errors import DatasetError, MissingDependency
from normpos_grasp.perception.onnx_segmenter import CONF_METADATA_KEY, DEPTH_METADATA_KEY, DepthChannelSpec
from normpos_grasp.training.data import (
    CLASS_NAMES,
    Sample,
    assign_cells,
    pack_sample,
    read_shards,
    synth_samples,
    write_shard,
)

if TYPE_CHECKING:
    import torch

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainOptions:
    """Training settings.

    input_hw: network input (H, W) pixels, multiples of 32; width: base channel width of the network;
    num_protos: prototype masks; steps: optimiser steps; batch: images per step; lr: peak AdamW learning rate
    (cosine decay, 200 warm-up steps); weight_decay: AdamW decay; threads: torch CPU threads; seed: RNG seed;
    time_limit_s: stop early after this many seconds of training (0 = no limit; a run that hits it is recorded as
    such in train.json and is reproducible only up to the step it reached); init_from: a .pt state dict to start
    from (fine-tuning a previous run) instead of random weights; checkpoint_every: write out_dir/normpos_seg.pt (+
    train.json) every this many steps (0 = only at the end), so a long run that is stopped keeps its weights. With a
    time limit the cosine learning-rate decay follows whichever is further along, steps or time, so a run cut by the
    limit still ends at a small learning rate.
    """

    input_hw: tuple[int, int] = (192, 256)
    width: int = 32
    num_protos: int = 32
    steps: int = 3000
    batch: int = 16
    lr: float = 4e-3
    weight_decay: float = 5e-4
    threads: int = 2
    seed: int = 0
    time_limit_s: float = 0.0
    init_from: str = ""
    checkpoint_every: int = 0


def _torch() -> object:
    try:
        import torch
    except ImportError as exc:
        raise MissingDependency("torch", "train", "training the segmentation model") from exc
    return torch


def generate_shards(
    folder: Path,
    seeds: range,
    input_hw: tuple[int, int],
    views: int = 2,
    shard_size: int = 25,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Render scenes `seeds` (each `views` views) and write shard_<first seed>.npz files into `folder`;
    shards already present are kept (generation resumes)."""
    folder.mkdir(parents=True, exist_ok=True)
    spec = DepthChannelSpec()
    for start in range(seeds.start, seeds.stop, shard_size):
        path = folder / f"shard_{start:07d}.npz"
        stop = min(start + shard_size, seeds.stop)
        if not path.exists():
            packed = [pack_sample(s, input_hw, spec) for seed in range(start, stop) for s in synth_samples(seed, views)]
            write_shard(path, packed)
        if progress is not None:
            progress(stop - start)


def generate_sample_shards(
    folder: Path,
    prefix: str,
    seeds: range,
    input_hw: tuple[int, int],
    make: Callable[[int], list[Sample]],
    shard_size: int = 25,
    progress: Callable[[int], None] | None = None,
) -> None:
    """Like `generate_shards` for any sample source: `make(seed)` gives the samples of one seed (for example
    `data.cell_samples` or `data.frame_samples`); files are named shard_<prefix>_<first seed>.npz and kept if
    present."""
    folder.mkdir(parents=True, exist_ok=True)
    spec = DepthChannelSpec()
    for start in range(seeds.start, seeds.stop, shard_size):
        path = folder / f"shard_{prefix}_{start:07d}.npz"
        stop = min(start + shard_size, seeds.stop)
        if not path.exists():
            write_shard(path, [pack_sample(s, input_hw, spec) for seed in range(start, stop) for s in make(seed)])
        if progress is not None:
            progress(stop - start)


def _giou(p: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """GIoU of (P, 4) xyxy tensors."""
    import torch

    ix1, iy1 = torch.max(p[:, 0], t[:, 0]), torch.max(p[:, 1], t[:, 1])
    ix2, iy2 = torch.min(p[:, 2], t[:, 2]), torch.min(p[:, 3], t[:, 3])
    inter = (ix2 - ix1).clamp(min=0) * (iy2 - iy1).clamp(min=0)
    ap = (p[:, 2] - p[:, 0]) * (p[:, 3] - p[:, 1])
    at = (t[:, 2] - t[:, 0]) * (t[:, 3] - t[:, 1])
    union = ap + at - inter + 1e-6
    iou = inter / union
    cx1, cy1 = torch.min(p[:, 0], t[:, 0]), torch.min(p[:, 1], t[:, 1])
    cx2, cy2 = torch.max(p[:, 2], t[:, 2]), torch.max(p[:, 3], t[:, 3])
    c = (cx2 - cx1) * (cy2 - cy1) + 1e-6
    return iou - (c - union) / c


def train(data_dir: Path, out_dir: Path, options: TrainOptions, log: Callable[[str], None] | None = None) -> Path:
    """Train on the shards in `data_dir`, write `out_dir`/normpos_seg.onnx (+ .pt, train.json); returns the ONNX
    path."""
    _torch()
    import torch
    from torch.nn import functional as F

    from normpos_grasp.training.model import SegNet, anchor_centres

    torch.manual_seed(options.seed)
    torch.set_num_threads(options.threads)
    torch.use_deterministic_algorithms(True)
    rng = np.random.default_rng(options.seed)
    xs, ms, bs, cs = read_shards(data_dir)
    if xs.shape[2:] != tuple(options.input_hw):
        raise DatasetError(f"shards in {data_dir} are {xs.shape[2:]}, training input is {options.input_hw}")
    logger.info("training on %d frames, %d instances", len(xs), sum(len(b) for b in bs))
    ih, iw = options.input_hw
    net = SegNet(xs.shape[1], len(CLASS_NAMES), options.num_protos, options.width)
    if options.init_from:
        net.load_state_dict(torch.load(options.init_from, map_location="cpu"))
    stride = net.stride
    centres_t = anchor_centres(ih // stride, iw // stride, stride)
    centres = centres_t.numpy()
    opt = torch.optim.AdamW(net.parameters(), lr=options.lr, weight_decay=options.weight_decay)
    warm = min(200, options.steps // 10)

    def lr_at(step: int, elapsed_s: float = 0.0) -> float:
        if step < warm:
            return options.lr * (step + 1) / warm
        frac = (step - warm) / max(1, options.steps - warm)
        if options.time_limit_s > 0:
            frac = max(frac, elapsed_s / options.time_limit_s)
        return options.lr * 0.5 * (1 + np.cos(np.pi * min(frac, 1.0)))

    def save(steps_done: int) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = out_dir / "normpos_seg.pt.tmp"
        torch.save(net.state_dict(), tmp)
        tmp.replace(out_dir / "normpos_seg.pt")
        info = {
            "options": asdict(options),
            "frames": len(xs),
            "steps_done": steps_done,
            "train_seconds": round(time.time() - t0, 1),
        }
        (out_dir / "train.json").write_text(json.dumps(info, indent=1))

    order = rng.permutation(len(xs))
    pos_ptr = 0
    t0 = time.time()
    net.train()
    steps_done = 0
    for step in range(options.steps):
        if options.time_limit_s > 0 and time.time() - t0 > options.time_limit_s:
            logger.warning("time limit reached after %d of %d steps", step, options.steps)
            break
        steps_done = step + 1
        if pos_ptr + options.batch > len(order):
            order = rng.permutation(len(xs))
            pos_ptr = 0
        idx = order[pos_ptr : pos_ptr + options.batch]
        pos_ptr += options.batch
        batch_x = np.empty((len(idx), xs.shape[1], ih, iw), np.float32)
        tb, tm, tc = [], [], []
        for j, i in enumerate(idx):
            x = xs[i].astype(np.float32)
            b, m, c = bs[i].copy(), ms[i], cs[i]
            if rng.random() < 0.5:
                x = x[:, :, ::-1]
                m = m[:, :, ::-1]
                b[:, [0, 2]] = iw - b[:, [2, 0]]
            if rng.random() < 0.5:
                x = x[:, ::-1, :]
                m = m[:, ::-1, :]
                b[:, [1, 3]] = ih - b[:, [3, 1]]
            x = x.copy()
            x[:3] = np.clip(x[:3] * rng.uniform(0.8, 1.2) + rng.uniform(-0.06, 0.06), 0, 1)
            batch_x[j] = x
            tb.append(b)
            tm.append(np.ascontiguousarray(m))
            tc.append(c)
        lr = lr_at(step, time.time() - t0)
        for group in opt.param_groups:
            group["lr"] = lr
        box, cls, coef, protos = net(torch.from_numpy(batch_x))
        bsz, nc = cls.shape[:2]
        cls = cls.flatten(2).transpose(1, 2)  # (B, A, nc)
        box = box.flatten(2).transpose(1, 2)  # (B, A, 4)
        coef = coef.flatten(2).transpose(1, 2)  # (B, A, nm)
        cls_target = torch.zeros_like(cls)
        loss_box = torch.zeros(())
        loss_mask = torch.zeros(())
        npos = 0
        for j in range(bsz):
            assign = assign_cells(tb[j], tm[j], centres, stride)
            pos = np.flatnonzero(assign >= 0)
            if len(pos) == 0:
                continue
            g = assign[pos]
            npos += len(pos)
            pos_t = torch.from_numpy(pos)
            cls_target[j, pos_t, torch.from_numpy(tc[j][g])] = 1.0
            c = centres_t[pos_t]
            pb = box[j, pos_t]
            pred_xyxy = torch.stack([c[:, 0] - pb[:, 0], c[:, 1] - pb[:, 1], c[:, 0] + pb[:, 2], c[:, 1] + pb[:, 3]], 1)
            gt_xyxy = torch.from_numpy(tb[j][g]).float()
            loss_box = loss_box + (1 - _giou(pred_xyxy, gt_xyxy)).sum()
            mh, mw = protos.shape[-2:]
            logits = coef[j, pos_t] @ protos[j].reshape(protos.shape[1], -1)  # (P, mh*mw)
            gt_m = torch.from_numpy(tm[j][g].reshape(len(pos), -1)).float()
            gb = gt_xyxy / 4.0
            yy = torch.arange(mh).float()[:, None] + 0.5
            xx = torch.arange(mw).float()[None, :] + 0.5
            crop = (
                (
                    (xx[None] >= gb[:, 0, None, None] - 1)
                    & (xx[None] <= gb[:, 2, None, None] + 1)
                    & (yy[None] >= gb[:, 1, None, None] - 1)
                    & (yy[None] <= gb[:, 3, None, None] + 1)
                )
                .reshape(len(pos), -1)
                .float()
            )
            bce = F.binary_cross_entropy_with_logits(logits, gt_m, reduction="none")
            loss_mask = loss_mask + ((bce * crop).sum(1) / crop.sum(1).clamp(min=1)).sum()
        npos_f = float(max(npos, 1))
        p = torch.sigmoid(cls)
        ce = F.binary_cross_entropy_with_logits(cls, cls_target, reduction="none")
        pt = p * cls_target + (1 - p) * (1 - cls_target)
        alpha = 0.25 * cls_target + 0.75 * (1 - cls_target)
        loss_cls = (alpha * (1 - pt) ** 2 * ce).sum() / npos_f
        loss = loss_cls + 2.0 * loss_box / npos_f + 3.0 * loss_mask / npos_f
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 10.0)
        opt.step()
        if log is not None and (step % 25 == 0 or step < 5 or step == options.steps - 1):
            log(
                f"step {step}/{options.steps} loss {float(loss.detach()):.3f} cls {float(loss_cls.detach()):.3f} "
                f"box {float(loss_box.detach()) / npos_f:.3f} mask {float(loss_mask.detach()) / npos_f:.3f} "
                f"lr {lr:.2e} {time.time() - t0:.0f}s"
            )
        if options.checkpoint_every > 0 and steps_done % options.checkpoint_every == 0:
            save(steps_done)
    save(steps_done)
    return export_onnx(net, out_dir / "normpos_seg.onnx", options)


def export_onnx(net: object, path: Path, options: TrainOptions, conf_threshold: float = 0.3) -> Path:
    """Export `net` (a SegNet) in the YOLOv8-seg layout with class names, the depth spec and the recommended
    confidence threshold in the metadata."""
    import onnx
    import torch

    from normpos_grasp.training.model import ExportWrapper, SegNet

    assert isinstance(net, SegNet)
    net.eval()
    wrapper = ExportWrapper(net, options.input_hw)
    dummy = torch.zeros(1, 4, *options.input_hw)
    torch.onnx.export(
        wrapper,
        (dummy,),
        str(path),
        input_names=["images"],
        output_names=["output0", "output1"],
        opset_version=17,
        dynamo=False,
    )
    model = onnx.load(str(path))
    meta = {
        "names": json.dumps(list(CLASS_NAMES)),
        "channels": "4",
        DEPTH_METADATA_KEY: DepthChannelSpec().to_json(),
        "imgsz": json.dumps(list(options.input_hw)),
        "stride": "8",
        "task": "segment",
        "author": "normpos-grasp",
        "description": "normpos-grasp bundled YOLACT-style RGB-D part segmenter, trained on synthetic scenes",
        "train_seed": str(options.seed),
        CONF_METADATA_KEY: str(conf_threshold),
    }
    for k, v in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.save(model, str(path))
    return path
