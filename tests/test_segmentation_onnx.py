"""OnnxSegmenter: the decoder against a plain reference implementation of the YOLOv8-seg layout, on a model
written by the ultralytics exporter (tests/fixtures/segmentation/make_fixture.py), and bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import onnx
import onnxruntime  # noqa: F401  (a hard dependency: imported, never skipped)
import pytest

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.errors import InputError, ModelFormatError
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.perception.onnx_segmenter import (
    OnnxSegmenter,
    OnnxSegmenterOptions,
    letterbox_geometry,
)

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "segmentation" / "yolov8seg_tiny.onnx"
# the random-weight fixture scores about 0.005-0.15; a low threshold gives several detections
OPTS = OnnxSegmenterOptions(conf_threshold=0.02, iou_threshold=0.7, max_detections=40)


def _camera(w: int, h: int) -> Camera:
    return Camera(K=np.array([[500.0, 0, w / 2], [0, 500.0, h / 2], [0, 0, 1]]), width=w, height=h)


def _frame(seed: int, w: int = 160, h: int = 100) -> RGBDFrame:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    rgb = cv2.GaussianBlur(rgb, (0, 0), 3)  # some structure so detections differ between frames
    return RGBDFrame(rgb=rgb, depth_m=np.full((h, w), 0.8), camera=_camera(w, h))


def reference_decode(
    out0: np.ndarray,
    protos: np.ndarray,
    image_hw: tuple[int, int],
    input_hw: tuple[int, int],
    opts: OnnxSegmenterOptions,
) -> tuple[list[list[float]], list[float], list[int], list[np.ndarray]]:
    """Straightforward, loop-based decoding of the layout, written independently of the library code."""
    nm, mh, mw = protos.shape[1:]
    nc = out0.shape[1] - 4 - nm
    h0, w0 = image_hw
    ih, iw = input_hw
    r = min(ih / h0, iw / w0)
    nw, nh = round(w0 * r), round(h0 * r)
    left, top = round((iw - nw) / 2 - 0.1), round((ih - nh) / 2 - 0.1)
    cands = []
    for a in range(out0.shape[2]):
        col = out0[0, :, a]
        c = int(np.argmax(col[4 : 4 + nc]))
        s = float(col[4 + c])
        if s > opts.conf_threshold:
            cx, cy, bw, bh = (float(v) for v in col[:4])
            cands.append((s, c, [cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2], col[4 + nc :]))
    cands.sort(key=lambda t: -t[0])

    def iou(a: list[float], b: list[float]) -> float:
        iw_ = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
        ih_ = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
        inter = iw_ * ih_
        union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
        return inter / union if union > 0 else 0.0

    kept: list[tuple[float, int, list[float], np.ndarray]] = []
    for cand in cands:
        if all(k[1] != cand[1] or iou(k[2], cand[2]) <= opts.iou_threshold for k in kept):
            kept.append(cand)
    kept = kept[: opts.max_detections]
    boxes, scores, classes, masks = [], [], [], []
    for s, c, b, coef in kept:
        proto_mask = np.zeros((mh, mw), dtype=np.float64)
        for j in range(nm):
            proto_mask += float(coef[j]) * protos[0, j].astype(np.float64)
        prob = 1.0 / (1.0 + np.exp(-proto_mask))
        y0, x0 = round(top * mh / ih - 0.1), round(left * mw / iw - 0.1)
        y1, x1 = round((top + nh) * mh / ih + 0.1), round((left + nw) * mw / iw + 0.1)
        prob = cv2.resize(prob[y0:y1, x0:x1].astype(np.float32), (w0, h0), interpolation=cv2.INTER_LINEAR)
        fb = [(b[0] - left) / r, (b[1] - top) / r, (b[2] - left) / r, (b[3] - top) / r]
        fb = [min(max(fb[0], 0), w0), min(max(fb[1], 0), h0), min(max(fb[2], 0), w0), min(max(fb[3], 0), h0)]
        m = np.zeros((h0, w0), dtype=bool)
        for v in range(h0):
            for u in range(w0):
                if fb[0] - 1 < u < fb[2] and fb[1] - 1 < v < fb[3]:
                    m[v, u] = prob[v, u] > opts.mask_threshold
        boxes.append(fb)
        scores.append(s)
        classes.append(c)
        masks.append(m)
    return boxes, scores, classes, masks


@pytest.fixture(scope="module")
def seg() -> OnnxSegmenter:
    return OnnxSegmenter(FIXTURE, options=OPTS)


def test_fixture_reads_ultralytics_metadata(seg: OnnxSegmenter) -> None:
    assert isinstance(seg, Segmenter)
    assert seg.class_names == ["cube", "cylinder", "ring"]
    assert seg.input_hw == (96, 128)
    assert seg.channels == 3
    assert seg.num_prototypes == 32


@pytest.mark.parametrize(("seed", "w", "h"), [(0, 160, 100), (1, 128, 96), (2, 90, 150)])
def test_decoder_matches_reference(seg: OnnxSegmenter, seed: int, w: int, h: int) -> None:
    frame = _frame(seed, w, h)
    out0, out1, _ = seg.run_raw(frame.rgb)
    rb, rs, rc, rm = reference_decode(out0, out1, (h, w), seg.input_hw, OPTS)
    inst = seg.segment(frame)
    det = seg.detect(frame.rgb)
    assert len(rb) > 3, "the fixture should give several detections at this threshold"
    assert len(det.scores) == len(rb)
    np.testing.assert_allclose(det.boxes, np.array(rb), atol=1e-3)
    np.testing.assert_allclose(det.scores, rs, rtol=1e-6)
    assert det.classes.tolist() == rc
    for k in range(len(rb)):
        differing = int(np.sum(det.masks[k] != rm[k]))
        assert differing <= max(2, 0.002 * rm[k].size), f"detection {k}: {differing} mask pixels differ"
    nonempty = [k for k in range(len(rb)) if rm[k].any()]
    assert [i.label for i in inst] == [seg.class_names[rc[k]] for k in nonempty]
    assert [i.instance_id for i in inst] == list(range(1, len(inst) + 1))
    assert all(i.mask.shape == (h, w) for i in inst)


def test_letterbox_matches_ultralytics_rounding() -> None:
    lb = letterbox_geometry((480, 640), (96, 128))
    assert (lb.new_w, lb.new_h, lb.left, lb.top) == (128, 96, 0, 0)
    lb = letterbox_geometry((100, 160), (96, 128))
    assert (lb.new_w, lb.new_h, lb.left, lb.top) == (128, 80, 0, 8)


def test_high_threshold_gives_empty_result() -> None:
    seg = OnnxSegmenter(FIXTURE, options=OnnxSegmenterOptions(conf_threshold=0.9))
    assert seg.segment(_frame(0)) == []


def test_black_frame_is_handled(seg: OnnxSegmenter) -> None:
    f = _frame(0)
    black = RGBDFrame(rgb=np.zeros_like(f.rgb), depth_m=np.zeros_like(f.depth_m), camera=f.camera)
    for inst in seg.segment(black):
        assert inst.mask.shape == f.depth_m.shape


def test_bad_input(seg: OnnxSegmenter, tmp_path: Path) -> None:
    with pytest.raises(InputError):
        seg.run_raw(np.zeros((50, 60), dtype=np.uint8))
    with pytest.raises(InputError):
        seg.run_raw(np.zeros((50, 60, 4), dtype=np.uint8))
    with pytest.raises(InputError):
        seg.run_raw(np.zeros((50, 60, 3), dtype=np.float32))
    with pytest.raises(InputError):
        seg.run_raw(np.zeros((50, 60, 3), dtype=np.uint8), np.zeros((40, 60)))
    with pytest.raises(InputError):
        seg.segment("not a frame")  # type: ignore[arg-type]
    with pytest.raises(ModelFormatError):
        OnnxSegmenter(tmp_path / "missing.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx file")
    with pytest.raises(ModelFormatError):
        OnnxSegmenter(bad)
    with pytest.raises(ModelFormatError):
        OnnxSegmenter(FIXTURE, class_names=["only", "two"])


def test_model_without_prototypes_is_rejected(tmp_path: Path) -> None:
    model = onnx.load(str(FIXTURE))
    del model.graph.output[1]
    path = tmp_path / "det_only.onnx"
    onnx.save(model, str(path))
    with pytest.raises(ModelFormatError, match="output1"):
        OnnxSegmenter(path)


def test_side_file_names_override_metadata(tmp_path: Path) -> None:
    path = tmp_path / "m.onnx"
    path.write_bytes(FIXTURE.read_bytes())
    path.with_suffix(".names.json").write_text('["a", "b", "c"]')
    assert OnnxSegmenter(path).class_names == ["a", "b", "c"]
