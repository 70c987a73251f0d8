"""Re-run a bundle's perception and planning offline and say what differs from the recorded cycle.

The replay takes the bundle's frame as captured, its cell file, its options (seeds included) and start joints, and
the same templates (checked by SHA-256), and runs `pipeline.process_frame`. A bundle whose segmenter can be remade
(the bundled model, the depth segmenter) is segmented again; otherwise (true masks of a synthetic or BOP source, a
custom segmenter) its recorded masks are the input. Compared: masks (IoU, matched greedily by overlap), fits
(template, accepted, pose delta in mm / deg), the plan (status, grasp chosen, joint waypoints and trajectory max
|dq|) and the plan JSON bytes without its `timing_ms` (wall-clock stage times, the one field that differs between
runs by nature).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.perception.base import Segmenter
from normpos_grasp.pipeline import FrameResult, PipelineOptions, process_frame
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.template import Template
from normpos_grasp.replay.bundle import Bundle, fit_entries, load_bundle, load_library_record, template_sha256


@dataclass(frozen=True)
class Row:
    """One line of the summary table: what, recorded, replayed, the difference, whether it is the same, and whether
    it is an input of the replay ('input': templates, options, frame, model) or a result ('result')."""

    item: str
    recorded: str
    replayed: str
    difference: str
    same: bool
    kind: str = "result"


@dataclass(frozen=True, eq=False)
class ReplayReport:
    """Outcome of `replay_bundle`. identical: every result row the same (masks, fits, the plan JSON byte for byte
    without timing_ms; a changed input with the same results is still identical); rows: the summary table;
    plan_json: the replayed plan (None when none); result: the replayed FrameResult."""

    bundle: Path
    rows: tuple[Row, ...]
    plan_json: dict[str, Any] | None
    result: FrameResult
    notes: tuple[str, ...] = ()

    @property
    def identical(self) -> bool:
        return all(r.same for r in self.rows if r.kind == "result")

    def table(self) -> str:
        """The rows as an aligned text table (one header line, one line per row); first column '=' same, '!' a
        result that differs, '~' an input that was changed."""
        head = ("", "item", "recorded", "replayed", "difference")
        marks = [("=" if r.same else "!" if r.kind == "result" else "~") for r in self.rows]
        lines = [head] + [
            (m, r.item, r.recorded, r.replayed, r.difference) for m, r in zip(marks, self.rows, strict=True)
        ]
        widths = [max(len(line[k]) for line in lines) for k in range(4)]
        return "\n".join(
            "  ".join(cell.ljust(widths[k]) for k, cell in enumerate(line[:4])) + "  " + line[4] for line in lines
        ).rstrip()

    def to_json(self) -> dict[str, Any]:
        return {
            "bundle": str(self.bundle),
            "identical": self.identical,
            "rows": [r.__dict__ for r in self.rows],
            "notes": list(self.notes),
        }


def canonical_plan_bytes(plan_json: dict[str, Any] | None) -> bytes:
    """The plan JSON without `timing_ms` (wall-clock stage times), keys sorted: what must match byte for byte."""
    if plan_json is None:
        return b"null"
    doc = {k: v for k, v in plan_json.items() if k != "timing_ms"}
    return json.dumps(doc, sort_keys=True, indent=1).encode("utf-8")


class _RecordedMasks:
    """A segmenter that gives the bundle's recorded instances for its frame."""

    def __init__(self, instances: tuple[Instance, ...]) -> None:
        self.instances = instances

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        return list(self.instances)


def remake_segmenter(bundle: Bundle) -> Segmenter:
    """The bundle's segmenter made again ('model': the ONNX file it names, 'depth'), else its recorded masks."""
    spec = bundle.segmenter
    kind = spec.get("kind")
    if kind == "depth":
        from normpos_grasp.perception.depth_segmenter import DepthSegmenter, DepthSegmenterOptions
        from normpos_grasp.replay.options import options_from_json

        return DepthSegmenter(options_from_json(DepthSegmenterOptions, spec.get("options", {}), "segmenter.options"))
    if kind == "model":
        from normpos_grasp.perception.onnx_segmenter import OnnxSegmenter, OnnxSegmenterOptions
        from normpos_grasp.replay.options import options_from_json

        opts = options_from_json(OnnxSegmenterOptions, spec.get("options", {}), "segmenter.options")
        return OnnxSegmenter(spec.get("model_path"), options=opts)
    return _RecordedMasks(bundle.instances)


def replay_bundle(
    bundle: Bundle | str | Path,
    *,
    options: PipelineOptions | None = None,
    frame: RGBDFrame | None = None,
    library: list[Template] | None = None,
    models: Sequence[str | Path] = (),
    segmenter: Segmenter | None = None,
) -> ReplayReport:
    """Re-run the bundle's cycle and compare it with the recording.

    options / frame / library / segmenter: replace the recorded ones (what-if runs, or a test that perturbs an
    input); models: load the templates from these `resolve_library` entries instead of the recorded ones.
    Raises BundleError for a bundle that is not one, InputError when its templates cannot be found."""
    b = bundle if isinstance(bundle, Bundle) else load_bundle(bundle)
    notes: list[str] = [f"option {name} not in the bundle: today's default used" for name in b.missing_options]
    templates = library if library is not None else load_library_record(b.library, models)
    used_options = options if options is not None else b.options
    used_frame = frame if frame is not None else b.frame
    seg = segmenter if segmenter is not None else remake_segmenter(b)
    result = process_frame(used_frame, seg, templates, b.cell, used_options, b.start_q)
    plan_json = result.plan.to_json() if result.plan is not None else None
    rows: list[Row] = []
    rows.extend(_template_rows(b, templates))
    if segmenter is None and b.segmenter.get("kind") == "model":
        rows.append(_model_row(b.segmenter))
    rows.append(_options_row(b.options, used_options))
    rows.append(_frame_row(b.frame, used_frame))
    mapping, mask_rows = _mask_rows(b.instances, result.instances, isinstance(seg, _RecordedMasks) and frame is None)
    rows.extend(mask_rows)
    rows.extend(_fit_rows(list(b.fits), fit_entries(result), mapping))
    rows.extend(_plan_rows(b.plan, plan_json))
    return ReplayReport(b.path, tuple(rows), plan_json, result, tuple(notes))


class ReplayMismatch(AssertionError):
    """`assert_replays` found a difference; `report` is the replay's ReplayReport (its table is the message)."""

    def __init__(self, report: ReplayReport) -> None:
        super().__init__(f"replay of {report.bundle} differs from the recording:\n{report.table()}")
        self.report = report


def assert_replays(bundle: Bundle | str | Path, **overrides: Any) -> ReplayReport:
    """Test helper: replay `bundle` (keywords as for `replay_bundle`) and raise ReplayMismatch (an AssertionError)
    with the summary table unless every result is identical; returns the report. A bundle saved from a failing
    cycle, committed under tests/, thereby becomes a regression test:
    `def test_cycle(): assert_replays("tests/data/bundles/NAME")`."""
    report = replay_bundle(bundle, **overrides)
    if not report.identical:
        raise ReplayMismatch(report)
    return report


# ----------------------------------------------------------------------------------------------- comparison rows
def _template_rows(b: Bundle, templates: list[Template]) -> list[Row]:
    recorded = {str(e["name"]): str(e["sha256"]) for e in b.library.get("templates", [])}
    now = {t.name: template_sha256(t) for t in templates}
    changed = sorted(n for n in set(recorded) | set(now) if recorded.get(n) != now.get(n))
    same = not changed
    return [
        Row(
            "templates",
            f"{len(recorded)} ({';'.join(b.library.get('sources', []))})",
            f"{len(now)}",
            "same SHA-256" if same else "changed: " + ", ".join(changed),
            same,
            "input",
        )
    ]


def _model_row(spec: dict[str, Any]) -> Row:
    from normpos_grasp.replay.bundle import file_sha256

    path = Path(str(spec.get("model_path")))
    now = file_sha256(path) if path.is_file() else "missing"
    same = now == spec.get("model_sha256")
    return Row("segmentation model", path.name, path.name if now != "missing" else "missing",
               "same SHA-256" if same else "the model file changed", same, "input")  # fmt: skip


def _options_row(recorded: PipelineOptions, used: PipelineOptions) -> Row:
    from normpos_grasp.replay.options import options_to_json

    diff = _dict_diff(options_to_json(recorded), options_to_json(used))
    text = "; ".join(f"{k}: {a} -> {c}" for k, a, c in diff[:4]) + (" ..." if len(diff) > 4 else "")
    return Row("options", "recorded", "recorded" if not diff else "changed", text or "same", not diff, "input")


def _dict_diff(a: Any, b: Any, prefix: str = "") -> list[tuple[str, Any, Any]]:
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[tuple[str, Any, Any]] = []
        for k in sorted(set(a) | set(b)):
            out.extend(_dict_diff(a.get(k), b.get(k), f"{prefix}{k}."))
        return out
    return [] if a == b else [(prefix.rstrip("."), a, b)]


def _frame_row(recorded: RGBDFrame, used: RGBDFrame) -> Row:
    d0, d1 = np.asarray(recorded.depth_m), np.asarray(used.depth_m)
    if d0.shape != d1.shape:
        return Row("frame", f"{d0.shape}", f"{d1.shape}", "another frame size", False, "input")
    same_depth = bool(np.array_equal(d0, d1, equal_nan=True))
    same_rgb = bool(np.array_equal(recorded.rgb, used.rgb))
    same_cam = recorded.camera.to_dict() == used.camera.to_dict()
    if same_depth and same_rgb and same_cam:
        return Row("frame", "captured", "recorded frame", "same", True, "input")
    with np.errstate(invalid="ignore"):
        diff = np.abs(np.nan_to_num(d0) - np.nan_to_num(d1))
    parts = [] if same_depth else [f"depth max |d| {diff.max() * 1e3:.3f} mm on {int((diff > 0).sum())} px"]
    parts += [] if same_rgb else ["colour differs"]
    parts += [] if same_cam else ["camera differs"]
    return Row("frame", "captured", "replaced", "; ".join(parts), False, "input")


def _mask_rows(
    recorded: tuple[Instance, ...], replayed: list[Instance], reused: bool
) -> tuple[dict[int, int], list[Row]]:
    """(recorded instance id -> replayed instance id, rows): greedy matching by IoU."""
    pairs = []
    for i, a in enumerate(recorded):
        for j, c in enumerate(replayed):
            if a.mask.shape != c.mask.shape:
                continue
            inter = int(np.count_nonzero(a.mask & c.mask))
            if inter:
                pairs.append((inter / int(np.count_nonzero(a.mask | c.mask)), i, j))
    pairs.sort(key=lambda p: (-p[0], p[1], p[2]))
    used_i: set[int] = set()
    used_j: set[int] = set()
    mapping: dict[int, int] = {}
    ious: list[float] = []
    same_labels = True
    for iou, i, j in pairs:
        if i in used_i or j in used_j:
            continue
        used_i.add(i)
        used_j.add(j)
        mapping[recorded[i].instance_id] = replayed[j].instance_id
        ious.append(iou)
        same_labels &= recorded[i].label == replayed[j].label
    exact = (
        len(recorded) == len(replayed)
        and len(mapping) == len(recorded)
        and all(np.array_equal(a.mask, c.mask) for a, c in zip(recorded, replayed, strict=True))
        and same_labels
    )
    how = "recorded masks reused" if reused else "segmented again"
    if ious:
        diff = f"{how}; IoU min {min(ious):.4f}, mean {float(np.mean(ious)):.4f}"
    else:
        diff = f"{how}; no overlap"
    lost = len(recorded) - len(mapping)
    extra = len(replayed) - len(mapping)
    if lost or extra:
        diff += f"; {lost} recorded unmatched, {extra} new"
    if not same_labels:
        diff += "; labels differ"
    return mapping, [Row("masks", str(len(recorded)), str(len(replayed)), diff, exact)]


def _fit_rows(recorded: list[dict[str, Any]], replayed: list[dict[str, Any]], mapping: dict[int, int]) -> list[Row]:
    by_id = {int(f["instance_id"]): f for f in replayed}
    rows: list[Row] = []
    matched: set[int] = set()
    for f in recorded:
        rid = mapping.get(int(f["instance_id"]))
        g = by_id.get(rid) if rid is not None else None
        name = f"fit {f['instance_id']} {f['template']}"
        rec = _verdict(f)
        if g is None:
            rows.append(Row(name, rec, "-", "no fit for this object", False))
            continue
        matched.add(int(g["instance_id"]))
        rep = _verdict(g) + ("" if g["template"] == f["template"] else f" as {g['template']}")
        a = np.asarray(f["frame_from_object"], dtype=np.float64)
        c = np.asarray(g["frame_from_object"], dtype=np.float64)
        dt_mm = float(np.linalg.norm(a[:3, 3] - c[:3, 3]) * 1e3)
        cos = (np.trace(a[:3, :3].T @ c[:3, :3]) - 1.0) / 2.0
        dr_deg = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        same = f == {**g, "instance_id": f["instance_id"]}
        diff = f"{dt_mm:.3f} mm / {dr_deg:.3f} deg"
        if not same and dt_mm == 0.0 and dr_deg == 0.0:
            keys = sorted(k for k in f if k != "instance_id" and f[k] != g.get(k))
            diff += "; " + ", ".join(keys)
        rows.append(Row(name, rec, rep, diff, same))
    for g in replayed:
        if int(g["instance_id"]) not in matched:
            rows.append(Row(f"fit {g['instance_id']} {g['template']}", "-", "new", "a fit the recording lacks", False))
    return rows


def _verdict(fit: dict[str, Any]) -> str:
    """'accepted', or 'rejected (' + the first clause of the reason, at most 40 characters + ')'."""
    if fit["accepted"]:
        return "accepted"
    first = str(fit["reason"]).split(";")[0].split(" (")[0]
    return f"rejected ({first[:37] + '...' if len(first) > 40 else first})"


def _plan_rows(recorded: dict[str, Any] | None, replayed: dict[str, Any] | None) -> list[Row]:
    def status(p: dict[str, Any] | None) -> str:
        return "none" if p is None else str(p.get("status"))

    def grasp(p: dict[str, Any] | None) -> str:
        if p is None or not p.get("grasp"):
            return "-"
        t = p.get("target") or {}
        return f"{t.get('template')} #{t.get('instance')} {p['grasp'].get('id')}"

    rows = [Row("plan status", status(recorded), status(replayed), "", status(recorded) == status(replayed))]
    g0, g1 = grasp(recorded), grasp(replayed)
    rows.append(Row("grasp chosen", g0, g1, "same" if g0 == g1 else "another grasp", g0 == g1))
    w0 = (recorded or {}).get("joint_waypoints") or []
    w1 = (replayed or {}).get("joint_waypoints") or []
    rows.append(_q_row("joint waypoints", [w["q"] for w in w0], [w["q"] for w in w1],
                       [w["name"] for w in w0] == [w["name"] for w in w1]))  # fmt: skip
    s0 = ((recorded or {}).get("trajectory") or {}).get("samples") or []
    s1 = ((replayed or {}).get("trajectory") or {}).get("samples") or []
    rows.append(_q_row("trajectory samples", [s["q"] for s in s0], [s["q"] for s in s1],
                       [s["t"] for s in s0] == [s["t"] for s in s1]))  # fmt: skip
    b0, b1 = canonical_plan_bytes(recorded), canonical_plan_bytes(replayed)
    same = b0 == b1
    text = "identical (without timing_ms)" if same else _first_difference(recorded, replayed, b0, b1)
    rows.append(Row("plan JSON bytes", f"{len(b0)} B", f"{len(b1)} B", text, same))
    return rows


def _q_row(item: str, q0: list[Any], q1: list[Any], same_names: bool) -> Row:
    if len(q0) != len(q1):
        return Row(item, str(len(q0)), str(len(q1)), "different count", False)
    if not q0:
        return Row(item, "0", "0", "none", True)
    dq = float(np.max(np.abs(np.asarray(q0, dtype=np.float64) - np.asarray(q1, dtype=np.float64))))
    same = dq == 0.0 and same_names
    text = f"max |dq| {dq:.3g} rad" + ("" if same_names else "; names or times differ")
    return Row(item, str(len(q0)), str(len(q1)), text, same)


def _first_difference(p0: dict[str, Any] | None, p1: dict[str, Any] | None, a: bytes, b: bytes) -> str:
    """Where two canonical plan documents part: the first byte and the top-level keys whose values differ."""
    n = next((k for k in range(min(len(a), len(b))) if a[k] != b[k]), min(len(a), len(b)))
    keys = sorted(
        k for k in set(p0 or {}) | set(p1 or {}) if k != "timing_ms" and (p0 or {}).get(k) != (p1 or {}).get(k)
    )
    return f"differ from byte {n}" + (f": {', '.join(keys)}" if keys else "")


__all__ = [
    "ReplayMismatch",
    "ReplayReport",
    "Row",
    "assert_replays",
    "canonical_plan_bytes",
    "remake_segmenter",
    "replay_bundle",
]
