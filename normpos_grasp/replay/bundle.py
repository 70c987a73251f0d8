"""Replay bundles: everything one cycle of the cell loop saw, decided and did, in one folder.

Layout of a bundle (docs/replay.md):

    manifest.json     format, versions, sha256 and size of every other file (written last)
    cycle.json        index, status, check, fault, stage times, start joints, segmenter, library, frame ids
    options.json      the PipelineOptions of the cycle (every seed included)
    cell.yaml         the cell file as read (its path and SHA-256 are in cycle.json)
    camera.json       the camera, exact (Camera.to_dict)
    frame.npz         rgb (H, W, 3) uint8, depth_m (H, W) float64 as captured (before any depth-bias correction),
                      masks (K, H, W) bool: the exact input of the replay
    instances.json    label, score, instance_id, source_id of each mask
    bop/000000/       the same frame as a BOP scene (io.bop writer: mm, uint16 depth at 0.1 mm), masks in
                      mask_visib/, the cycle's accepted fits as scene_gt.json poses (obj_id: 1-based index in the
                      library; 0 for an instance without an accepted fit, identity pose)
    fits.json         every template fit: template, instance, accepted, reason, scores, pose (world or camera)
    plan.json         the plan as the loop had it (docs/grasping.md), or null
    execution.json    the execution report and the driver state trace (sampled by the recorder), or nulls
    scene.glb         the frame's glTF twin (report.frame.frame_twin, with candidate markers)

Atomic: a bundle is written into a hidden staging folder `.NAME.<random>.partial` beside its final name and renamed
into place after manifest.json; an error removes the staging folder. A reader refuses a folder without a manifest,
of another format, or whose files do not match their recorded SHA-256 (`BundleError`, one line).
"""

from __future__ import annotations

import contextlib
import datetime
import functools
import hashlib
import io
import json
import logging
import os
import platform
import shutil
import tempfile
import threading
import time
import zipfile
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from normpos_grasp.atomic import atomic_write_bytes
from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.cell.config import BoxSpec, CellConfig, cell_from_dict
from normpos_grasp.errors import InputError
from normpos_grasp.io.yaml_safe import load_yaml
from normpos_grasp.pipeline import FrameResult, PipelineOptions
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.template import Template
from normpos_grasp.replay.errors import BundleError
from normpos_grasp.replay.options import options_from_json, options_to_json
from normpos_grasp.replay.rtde_trace import RtdeTrace
from normpos_grasp.typing import FloatArray

if TYPE_CHECKING:
    from normpos_grasp.execution.driver import ArmDriver
    from normpos_grasp.perception.base import Segmenter

log = logging.getLogger(__name__)

BUNDLE_FORMAT = "normpos-grasp/replay-bundle@1"
MANIFEST = "manifest.json"
#: packages whose versions a manifest records (absent ones as null)
RECORDED_PACKAGES = ("numpy", "scipy", "trimesh", "opencv-python-headless", "onnxruntime", "pin", "ruckig", "mujoco")
#: drivers whose state trace comes from a separate RTDE connection (replay.rtde_trace)
RTDE_DRIVERS = ("RtdeDriver", "SupervisedRtdeDriver")
_REQUIRED = ("cycle.json", "options.json", "cell.yaml", "camera.json", "frame.npz", "instances.json", "fits.json")


class PickRecord(Protocol):
    """What a bundle takes from one turn of the loop (`loop.PickRecord` has these fields)."""

    @property
    def index(self) -> int: ...
    @property
    def result(self) -> FrameResult: ...
    @property
    def status(self) -> str: ...
    @property
    def check(self) -> str: ...
    @property
    def plan_json(self) -> dict[str, Any] | None: ...
    @property
    def execution(self) -> Any: ...
    @property
    def timings_ms(self) -> dict[str, float]: ...
    @property
    def fault(self) -> str: ...
    @property
    def captured(self) -> RGBDFrame | None: ...
    @property
    def start_q(self) -> FloatArray | None: ...


@dataclass(frozen=True, eq=False)
class Bundle:
    """A bundle read back. frame: as captured (the replay's input); instances: the recorded masks; fits: fits.json
    entries; plan: the recorded plan JSON (None when the cycle had none); start_q: (6,) rad the cycle planned from;
    library: {'sources': the `templates.library.resolve_library` entries, 'templates': [{'name', 'sha256'}]};
    segmenter: {'kind': 'model' | 'depth' | 'recorded', ...}; missing_options: option names the bundle lacked
    (defaults used)."""

    path: Path
    manifest: dict[str, Any]
    cycle: dict[str, Any]
    cell: CellConfig
    options: PipelineOptions
    frame: RGBDFrame
    instances: tuple[Instance, ...]
    fits: tuple[dict[str, Any], ...]
    plan: dict[str, Any] | None
    execution: dict[str, Any]
    start_q: FloatArray
    library: dict[str, Any]
    segmenter: dict[str, Any]
    missing_options: tuple[str, ...] = ()


def template_sha256(template: Template) -> str:
    """SHA-256 of what a template contributes to fitting and planning: name, label, shape, mass, mesh vertices and
    faces (float64 / int64 bytes), control points, symmetries and grasp annotations."""
    h = hashlib.sha256()
    h.update(json.dumps([template.name, template.label, template.shape, float(template.mass_kg)]).encode())
    h.update(np.ascontiguousarray(template.mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(template.mesh.faces, dtype=np.int64).tobytes())
    for name in sorted(template.control_points):
        h.update(name.encode())
        h.update(np.asarray(template.control_points[name], dtype=np.float64).tobytes())
    for axis, point in template.symmetry.continuous:
        h.update(np.asarray(axis, dtype=np.float64).tobytes() + np.asarray(point, dtype=np.float64).tobytes())
    for t in template.symmetry.discrete:
        h.update(np.asarray(t, dtype=np.float64).tobytes())
    for g in template.grasps:
        h.update(json.dumps([g.id, g.scheme, g.opening_m, g.priority, g.approach_m, g.retreat_m, g.tilt_cone_rad])
                 .encode())  # fmt: skip
        h.update(np.asarray(g.object_from_tcp, dtype=np.float64).tobytes())
        if g.free_axis is not None:
            h.update(np.asarray(g.free_axis, dtype=np.float64).tobytes())
    return h.hexdigest()


def segmenter_record(segmenter: Segmenter) -> dict[str, Any]:
    """How a replay remakes `segmenter`: the bundled ONNX model (path, SHA-256, options) or the depth segmenter
    (options) are re-run; any other (true masks, a custom segmenter) is 'recorded': its masks are the input."""
    from normpos_grasp.perception.depth_segmenter import DepthSegmenter

    if isinstance(segmenter, DepthSegmenter):
        return {"kind": "depth", "options": options_to_json(segmenter.options)}
    model_path = getattr(segmenter, "model_path", None)
    if type(segmenter).__name__ == "OnnxSegmenter" and model_path is not None:
        return {
            "kind": "model",
            "model_path": str(model_path),
            "model_sha256": file_sha256(Path(model_path)),
            "options": options_to_json(segmenter.options),  # type: ignore[attr-defined]
        }
    return {"kind": "recorded", "type": type(segmenter).__name__}


def library_record(templates: Sequence[Template], sources: Sequence[str | Path] = ()) -> dict[str, Any]:
    """The library record of a bundle. sources: the `templates.library.resolve_library` entries the templates
    come from (folders, 'builtin'); empty for the built-in parts, which every template must then be, unchanged.
    Raises InputError."""
    from normpos_grasp.templates.library import BUILTIN, builtin_library

    entries = [{"name": t.name, "sha256": template_sha256(t)} for t in templates]
    if not sources:
        parts = {t.name: template_sha256(t) for t in builtin_library()}
        foreign = [e["name"] for e in entries if parts.get(e["name"]) != e["sha256"]]
        if foreign:
            raise InputError(
                f"templates {foreign} are not the built-in parts: tell the bundle recorder the libraries they come "
                "from (library_sources)"
            )
    resolved = [s if str(s) == BUILTIN else str(Path(s).resolve()) for s in sources] or [BUILTIN]
    return {"sources": [str(s) for s in resolved], "templates": entries}


def load_library_record(record: dict[str, Any], override: Sequence[str | Path] = ()) -> list[Template]:
    """The templates of a library record, in recorded order, from its sources (or the `override` entries)."""
    from normpos_grasp.templates.library import resolve_library

    sources = [str(p) for p in override] or [str(p) for p in record.get("sources", [])]
    available = {t.name: t for t in resolve_library(sources)}
    names = [str(e["name"]) for e in record.get("templates", [])]
    lost = [n for n in names if n not in available]
    if lost:
        raise InputError(f"the template library {';'.join(sources)} lacks the bundle's templates {lost}")
    return [available[n] for n in names]


# ----------------------------------------------------------------------------------------------- writing
def write_bundle(
    path: str | Path,
    record: PickRecord,
    cell: CellConfig,
    templates: Sequence[Template],
    options: PipelineOptions,
    *,
    segmenter: dict[str, Any],
    library: dict[str, Any],
    trace: dict[str, Any] | None = None,
) -> Path:
    """Write the bundle of one loop record to the folder `path` (which must not exist yet); returns it.

    record: a PickRecord with its captured frame and start joints (`loop.run_cell_loop` fills them);
    segmenter / library: `segmenter_record` and `library_record`; trace: the driver state trace of the cycle.
    Raises InputError when the record lacks its frame, or when the cell was not read from a file (or its file
    changed since), and FileExistsError when `path` exists."""
    target = Path(path)
    frame, start_q = record.captured, record.start_q
    if frame is None or start_q is None:
        raise InputError("a bundle needs the record's captured frame and start joints (run_cell_loop sets them)")
    cell_bytes = _cell_bytes(cell)
    if target.exists():
        raise FileExistsError(f"bundle {target} exists already")
    target.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent))
    try:
        files = _write_contents(
            stage, frame, start_q, record, cell, cell_bytes, list(templates), options, segmenter, library, trace
        )
        manifest = {
            "format": BUNDLE_FORMAT,
            "created_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ"),
            "versions": dict(_versions()),
            "files": {
                name: {"sha256": file_sha256(stage / name), "bytes": (stage / name).stat().st_size}
                for name in sorted(files)
            },  # fmt: skip
        }
        atomic_write_bytes(stage / MANIFEST, _json_bytes(manifest))
        os.chmod(stage, 0o777 & ~_umask())
        os.rename(stage, target)  # atomic; fails (OSError) rather than replace a folder that appeared meanwhile
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return target


def _write_contents(
    stage: Path,
    frame: RGBDFrame,
    start_q: FloatArray,
    record: PickRecord,
    cell: CellConfig,
    cell_bytes: bytes,
    templates: list[Template],
    options: PipelineOptions,
    segmenter: dict[str, Any],
    library: dict[str, Any],
    trace: dict[str, Any] | None,
) -> list[str]:
    from normpos_grasp.io.bop import BopGT, BopSceneWriter
    from normpos_grasp.report.frame import frame_twin

    result: FrameResult = record.result
    written: list[str] = []

    def put(name: str, data: bytes) -> None:
        (stage / name).parent.mkdir(parents=True, exist_ok=True)
        (stage / name).write_bytes(data)
        written.append(name)

    instances = list(result.instances)
    cycle = {
        "index": record.index,
        "status": record.status,
        "check": record.check,
        "fault": record.fault,
        "timings_ms": {k: float(v) for k, v in record.timings_ms.items()},
        "start_q": [float(v) for v in start_q],
        "frame": {"stamp": float(frame.stamp), "scene_id": int(frame.scene_id), "im_id": int(frame.im_id)},
        "cell": {**cell.record(), "name": cell.name},
        # what the loop changed in the cell by this turn (place patterns): the places left, every static box
        "cell_state": {
            "places": [p.name for p in cell.places],
            "static_boxes": [
                {
                    "name": b.name,
                    "world_from_box": np.asarray(b.world_from_box).tolist(),
                    "size": list(map(float, b.size)),
                }
                for b in cell.static_boxes
            ],
            # several bins: the bin the turn planned from first (the loop takes the bins in turn)
            **({"bin": cell.bin.name} if cell.bin is not None and len(cell.bins) > 1 else {}),
        },
        "segmenter": segmenter,
        "library": library,
        "depth_check": None if result.depth_check is None else {"corrected_m": float(result.depth_check.corrected)},
    }
    put("cycle.json", _json_bytes(cycle))
    put("options.json", _json_bytes(options_to_json(options)))
    put("cell.yaml", cell_bytes)
    put("camera.json", _json_bytes(frame.camera.to_dict()))
    h, w = frame.depth_m.shape
    masks = np.stack([i.mask for i in instances]) if instances else np.zeros((0, h, w), dtype=bool)
    put("frame.npz", _npz_bytes(rgb=np.asarray(frame.rgb), depth_m=np.asarray(frame.depth_m), masks=masks))
    put(
        "instances.json",
        _json_bytes(
            [
                {
                    "instance_id": int(i.instance_id),
                    "label": i.label,
                    "score": float(i.score),
                    "source_id": int(i.source_id),
                }
                for i in instances
            ]
        ),  # fmt: skip
    )
    put("fits.json", _json_bytes([_fit_entry(f) for f in result.fits]))
    put("plan.json", _json_bytes(record.plan_json))
    execution = {
        "report": None if record.execution is None else record.execution.to_dict(),
        "trace": trace,
    }
    put("execution.json", _json_bytes(execution))
    # the frame as a BOP scene: the masks with the accepted fits as poses (the template's obj_id, else its
    # 1-based place in the library)
    index_of = {t.name: (t.obj_id if t.obj_id > 0 else k + 1) for k, t in enumerate(templates)}
    accepted = {f.instance_id: f for f in result.fits if f.accepted}
    camera_from_world = frame.camera.camera_from_world if frame.camera.world_from_camera is not None else None
    gts = []
    for inst in instances:
        fit = accepted.get(inst.instance_id)
        if fit is None:
            gts.append(BopGT(0, np.eye(4)))
            continue
        pose = fit.frame_from_object
        if fit.frame == "world" and camera_from_world is not None:
            pose = camera_from_world @ pose
        gts.append(BopGT(index_of.get(fit.template.name, 0), pose))
    bop_camera = frame.camera if not frame.camera.has_distortion else None
    if bop_camera is not None:
        with BopSceneWriter(stage / "bop" / "000000") as writer:
            masks_list = [i.mask for i in instances]
            writer.add_frame(0, np.asarray(frame.rgb), frame.depth_m, bop_camera, gts, masks_list, masks_list)
        written.extend(str(p.relative_to(stage)) for p in sorted((stage / "bop").rglob("*")) if p.is_file())
    else:
        log.warning("bundle: the camera has lens distortion, which BOP cannot store: no bop/ folder")
    twin = frame_twin(result, cell, candidates=True)
    twin.export_glb(stage / "scene.glb")
    written.append("scene.glb")
    return written


def _fit_entry(fit: Any) -> dict[str, Any]:
    return {
        "instance_id": int(fit.instance_id),
        "template": fit.template.name,
        "accepted": bool(fit.accepted),
        "reason": fit.reason,
        "score": float(fit.score),
        "rmse_m": float(fit.rmse_m),
        "inlier_ratio": float(fit.inlier_ratio),
        "coverage": float(fit.coverage),
        "free_space_violation": float(fit.free_space_violation),
        "scale": float(fit.scale),
        "frame": fit.frame,
        "frame_from_object": np.asarray(fit.frame_from_object, dtype=np.float64).tolist(),
    }


def fit_entries(result: FrameResult) -> list[dict[str, Any]]:
    """fits.json entries of a frame result (what a replay compares)."""
    return [_fit_entry(f) for f in result.fits]


def _cell_bytes(cell: CellConfig) -> bytes:
    if cell.source is None:
        raise InputError(f"cell {cell.name!r} was built in memory: bundles need a cell read from a YAML file")
    data = Path(cell.source).read_bytes()
    if cell.source_sha256 and hashlib.sha256(data).hexdigest() != cell.source_sha256:
        raise InputError(f"the cell file {cell.source} changed since it was read: the bundle cannot record it")
    return data


# ----------------------------------------------------------------------------------------------- the recorder
class BundleRecorder:
    """Saves one bundle per loop record into `directory` (`run_cell_loop(..., bundles=recorder)`), named
    `<start UTC>-cycle<NNN>`. With a driver, a state trace is sampled every `trace_period_s` seconds and each bundle
    gets the samples since the previous one: for an RTDE driver by `replay.rtde_trace` (its own process and RTDE
    connection, never the driver's), for any other driver (the simulated one) by `driver.state()` from a thread.

    segmenter: the segmenter of the loop (recorded by `segmenter_record`); library_sources: the
    `templates.library.resolve_library` entries the loop's templates come from (empty: the built-in parts).
    background: write bundles in one writer thread while the loop goes on; `wait()` blocks until they are written
    (`run` calls it before each plan is executed, so no write overlaps arm motion); a failed write is raised by
    the next `save`, `wait` or `close`. `saved` lists the bundles written so far, in order.
    Use as a context manager: leaving it waits for pending writes and stops the sampler."""

    def __init__(
        self,
        directory: str | Path,
        segmenter: Segmenter,
        *,
        library_sources: Sequence[str | Path] = (),
        driver: ArmDriver | None = None,
        trace_period_s: float = 0.2,
        background: bool = False,
    ) -> None:
        if not trace_period_s > 0.0:
            raise InputError(f"trace_period_s must be positive, got {trace_period_s}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.run_id = datetime.datetime.now(datetime.UTC).strftime("%Y%m%dT%H%M%SZ")
        self.segmenter = segmenter_record(segmenter)
        self.library_sources = tuple(library_sources)
        self.saved: list[Path] = []
        self.save_times_s: list[float] = []
        self._library: dict[str, Any] | None = None
        self._library_key: tuple[int, ...] = ()
        self._period = float(trace_period_s)
        self._samples: list[dict[str, Any]] = []
        self._trace_note = ""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._trace_source = ""
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="bundle-writer") if background else None
        self._pending: list[Future[Path]] = []
        self._failure: BaseException | None = None
        self._rtde: RtdeTrace | None = None
        host = getattr(driver, "host", None)
        if driver is not None and type(driver).__name__ in RTDE_DRIVERS and isinstance(host, str):
            self._rtde = RtdeTrace(host, self._period)
            self._trace_source = f"ur_rtde RTDEReceiveInterface on its own connection to {host} (replay.rtde_trace)"
        elif driver is not None:
            self._thread = threading.Thread(target=self._sample, args=(driver,), name="bundle-trace", daemon=True)
            self._thread.start()
            self._trace_source = "driver.state() sampled by the bundle recorder"

    def __enter__(self) -> BundleRecorder:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
            return
        try:
            self.close()
        except Exception as failure:  # an exception is leaving already: log this one instead of masking it
            log.error("bundle recorder: %s: %s", type(failure).__name__, failure)

    def close(self) -> None:
        """Wait for pending writes, stop the state sampler (idempotent); raises a write that failed."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._rtde is not None:
            self._rtde.close()
        if self._writer is not None:
            self._writer.shutdown(wait=True)
            self._writer = None
        self._raise_failure()

    def wait(self) -> None:
        """Block until every pending bundle is written; raises a write that failed."""
        for future in list(self._pending):
            future.exception()  # waits
        self._raise_failure()

    def _raise_failure(self) -> None:
        for future in [f for f in self._pending if f.done()]:
            self._pending.remove(future)
            failure = future.exception()
            if failure is not None and self._failure is None:
                self._failure = failure
                raise failure

    def save(
        self, record: PickRecord, cell: CellConfig, templates: Sequence[Template], options: PipelineOptions
    ) -> Path:
        """Write the bundle of `record`; returns its folder."""
        t0 = time.perf_counter()
        key = tuple(id(t) for t in templates)
        if self._library is None or key != self._library_key:
            self._library = library_record(templates, self.library_sources)
            self._library_key = key
        with self._lock:
            samples, self._samples = self._samples, []
            note = self._trace_note
        if self._rtde is not None:
            samples, note = self._rtde.take()
        trace = None
        if self._trace_source:
            trace = {
                "source": self._trace_source,
                "period_s": self._period,
                "note": note,
                "samples": samples,
            }
        path = self.directory / f"{self.run_id}-cycle{record.index + 1:03d}"
        library = self._library

        def write() -> Path:
            t1 = time.perf_counter()
            out = write_bundle(
                path, record, cell, templates, options, segmenter=self.segmenter, library=library, trace=trace
            )
            self.saved.append(out)
            self.save_times_s.append(time.perf_counter() - t1 + prep_s)
            log.info("bundle %s written", out)
            return out

        prep_s = time.perf_counter() - t0
        if self._writer is None:
            return write()
        self._raise_failure()
        self._pending.append(self._writer.submit(write))
        return path

    def _sample(self, driver: ArmDriver) -> None:
        t0 = time.monotonic()
        while not self._stop.wait(self._period):
            try:
                s = driver.state()
            except Exception as exc:  # a faulted or disconnected driver: keep the trace, say why it has a gap
                with self._lock:
                    self._trace_note = f"state read failed at {time.monotonic() - t0:.2f} s: {type(exc).__name__}"
                continue
            sample = {
                "t_s": round(s.received_at - t0, 4),
                "controller_time_s": float(s.timestamp),
                "q": [float(v) for v in s.q],
                "qd": [float(v) for v in s.qd],
                "tcp_xyz_m": [float(v) for v in np.asarray(s.base_from_tcp)[:3, 3]],
                "robot_mode": int(s.robot_mode),
                "safety_mode": int(s.safety_mode),
                "safety_status_bits": int(s.safety_status_bits),
                "runtime_state": int(s.runtime_state),
                "program_running": bool(s.program_running),
                "digital_out": int(s.digital_out),
                "digital_in": int(s.digital_in),
            }
            with self._lock:
                self._samples.append(sample)


# ----------------------------------------------------------------------------------------------- reading
def list_bundles(directory: str | Path) -> list[Path]:
    """Complete bundles (folders with a manifest.json) directly under `directory`, sorted; staging folders
    (`.NAME.*.partial`) are skipped."""
    root = Path(directory)
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / MANIFEST).is_file())


def verify_bundle(path: str | Path) -> dict[str, Any]:
    """The manifest of the bundle at `path` after checking its format and every file's size and SHA-256."""
    root = Path(path)
    if not root.is_dir():
        raise BundleError(f"{root} is not a folder: a replay bundle is a folder with a {MANIFEST}")
    if root.name.endswith(".partial"):
        raise BundleError(f"{root} is a bundle that was never finished (its writer stopped): record the cycle again")
    mpath = root / MANIFEST
    if not mpath.is_file():
        raise BundleError(f"{root} has no {MANIFEST}: not a replay bundle (or an unfinished one)")
    try:
        manifest = json.loads(mpath.read_bytes())
    except ValueError as exc:
        raise BundleError(f"{mpath} is not JSON ({exc}): the bundle is corrupt") from exc
    if not isinstance(manifest, dict) or manifest.get("format") != BUNDLE_FORMAT:
        got = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise BundleError(f"{root} is not a {BUNDLE_FORMAT} bundle (format {got!r})")
    files = manifest.get("files")
    if not isinstance(files, dict) or any(n not in files for n in _REQUIRED):
        raise BundleError(f"{mpath} does not list the files a bundle holds ({', '.join(_REQUIRED)})")
    for name, entry in files.items():
        p = (root / name).resolve()
        if root.resolve() not in p.parents or not isinstance(entry, dict):
            raise BundleError(f"{mpath}: file entry {name!r} is malformed or points outside the bundle")
        if not p.is_file():
            raise BundleError(f"bundle {root}: {name} is missing")
        if p.stat().st_size != entry.get("bytes") or file_sha256(p) != entry.get("sha256"):
            raise BundleError(f"bundle {root}: {name} does not match its SHA-256 in {MANIFEST} (corrupt or edited)")
    return manifest


def load_bundle(path: str | Path) -> Bundle:
    """Read and verify a bundle (`verify_bundle`); every problem is one BundleError line."""
    root = Path(path)
    manifest = verify_bundle(root)
    cycle = _read_json(root / "cycle.json")
    if not isinstance(cycle, dict):
        raise BundleError(f"{root / 'cycle.json'}: expected an object")
    try:
        cell_info = dict(cycle["cell"])
        text = (root / "cell.yaml").read_text(encoding="utf-8")
        original = Path(cell_info["path"]) if "path" in cell_info else root / "cell.yaml"
        cell = replace(
            cell_from_dict(load_yaml(text, str(root / "cell.yaml")), base_dir=original.parent, source=original),
            source_sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(),
        )
        cell = _with_state(cell, cycle.get("cell_state"), root)
        missing: list[str] = []
        options = options_from_json(PipelineOptions, _read_json(root / "options.json"), "options", missing)
        camera = Camera.from_dict(_read_json(root / "camera.json"))
        with np.load(root / "frame.npz", allow_pickle=False) as data:
            rgb, depth, masks = data["rgb"], data["depth_m"], data["masks"]
        meta = cycle["frame"]
        frame = RGBDFrame(rgb, depth, camera, float(meta["stamp"]), int(meta["scene_id"]), int(meta["im_id"]))
        entries = _read_json(root / "instances.json")
        if len(entries) != len(masks) or masks.shape[1:] != depth.shape or masks.dtype != np.bool_:
            raise BundleError(
                f"bundle {root}: {len(entries)} instances but masks {masks.dtype} {masks.shape} for a frame of "
                f"{depth.shape}"
            )
        instances = tuple(
            Instance(np.asarray(m, dtype=bool), str(e["label"]), float(e["score"]), int(e["instance_id"]),
                     int(e["source_id"]))
            for e, m in zip(entries, masks, strict=True)
        )  # fmt: skip
        start_q = np.asarray(cycle["start_q"], dtype=np.float64)
        if start_q.shape != (6,):
            raise BundleError(f"bundle {root}: start_q must hold 6 joint angles, got {start_q.shape}")
        fits = tuple(_read_json(root / "fits.json"))
        plan = _read_json(root / "plan.json")
        execution = _read_json(root / "execution.json") if (root / "execution.json").is_file() else {}
        return Bundle(
            root, manifest, cycle, cell, options, frame, instances, fits, plan, execution, start_q,
            dict(cycle["library"]), dict(cycle["segmenter"]), tuple(missing),
        )  # fmt: skip
    except BundleError:
        raise
    except (KeyError, TypeError, ValueError, OSError, InputError) as exc:
        raise BundleError(f"bundle {root} is malformed: {type(exc).__name__}: {exc}") from exc


def _with_state(cell: CellConfig, state: Any, root: Path) -> CellConfig:
    """The cell file's cell as the turn had it: the recorded places left and static boxes (place patterns fill
    slots and leave parts as boxes during a run)."""
    if state is None:
        return cell
    by_name = {p.name: p for p in cell.places}
    names = [str(n) for n in state["places"]]
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise BundleError(f"bundle {root}: places {unknown} are not in its cell.yaml")
    boxes = tuple(
        BoxSpec(str(b["name"]), np.asarray(b["world_from_box"], dtype=np.float64), np.asarray(b["size"], dtype=float))
        for b in state["static_boxes"]
    )
    out = replace(cell, places=tuple(by_name[n] for n in names), static_boxes=boxes)
    if "bin" in state:
        try:
            out = out.picking_from(str(state["bin"]))
        except InputError as exc:
            raise BundleError(f"bundle {root}: {exc}") from exc
    return out


# ----------------------------------------------------------------------------------------------- helpers
def _npz_bytes(**arrays: np.ndarray) -> bytes:
    """An .npz archive (what `np.load` reads) deflated at level 1: noisy float64 depth barely compresses further at
    numpy's level 6, which costs several times the time."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for name, array in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def _json_bytes(data: Any) -> bytes:
    return json.dumps(data, indent=1).encode("utf-8")


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_bytes())
    except ValueError as exc:
        raise BundleError(f"{path} is not JSON: {exc}") from exc


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@functools.cache
def _versions() -> dict[str, str | None]:
    from normpos_grasp import __version__

    out: dict[str, str | None] = {"normpos_grasp": __version__, "python": platform.python_version()}
    for name in RECORDED_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def _umask() -> int:
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    return 0o022


__all__ = [
    "BUNDLE_FORMAT",
    "Bundle",
    "BundleRecorder",
    "fit_entries",
    "library_record",
    "list_bundles",
    "load_bundle",
    "load_library_record",
    "segmenter_record",
    "template_sha256",
    "verify_bundle",
    "write_bundle",
]
