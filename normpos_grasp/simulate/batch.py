"""Batches of simulated scenes: local processes (default) or Ray tasks, per-scene results, picks.csv and summary.json.

Scenes are independent and seeded from (config.seed, scene index), so the results do not depend on the number
of workers, on Ray, or on which scenes one process ran before: records are sorted by (scene, pick) before they
are written, and the written files hold no wall-clock times (those go to timing.json), so two runs with the same
seeds give byte-identical picks.csv, summary.json and plots.

A run folder (`RunFolder`) makes a batch resumable: `manifest.json` (the parameters that change results) is
written first, `scenes/scene_NNNNNN.json` atomically as each scene finishes, and `summary.json` last, which
marks the run complete. `run_batch(..., done=..., on_scene=...)` skips finished scenes and reports new ones.
SIGINT and SIGTERM during `run_batch` end the worker processes (pending scenes cancelled, running ones
killed) and raise `Interrupted`; workers also die with the parent (Linux: PR_SET_PDEATHSIG).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import io
import json
import logging
import math
import os
import shutil
from collections.abc import Callable, Collection, Mapping
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp import __version__
from normpos_grasp.atomic import atomic_write_bytes, atomic_write_text
from normpos_grasp.errors import InputError, MissingDependency, SimulationError
from normpos_grasp.planning.plan import PLANNING_PASSES
from normpos_grasp.simulate.episode import CAUSES, KINDS, PickRecord, SceneResult, SimulationConfig, run_scene
from normpos_grasp.simulate.signals import Interrupted, init_worker, signals_deferred, signals_ignored, signals_raise
from normpos_grasp.simulate.trace import LeftPart, cause_rows

logger = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]
SceneFn = Callable[[SceneResult], None]

#: Environment of scene workers (local processes and Ray tasks): single-threaded numerical libraries, so that
#: results do not depend on how many threads a worker could use.
THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}

#: Columns of picks.csv (deterministic; timings are in timing.json).
CSV_COLUMNS = (
    "scene",
    "pick",
    "success",
    "cause",
    "part",
    "template",
    "scheme",
    "physics",
    "reason",
    "depth_m",
    "occlusion",
    "fit_error_m",
    "slip_m",
    "lift_m",
    "parts_left",
    "captures",
    "fitted",
    "reused",
    "nudges",
    "nudge_collisions",
    "drags",
    "detail",
    "picture",
    "grasp_id",
    "kind",
    "plan_pass",
    "relaxed",
    "predicted_success",
)
#: summary key of the picks with no grasp chosen (give-ups) in the per-kind and per-pass breakdowns
NO_GRASP = "(no grasp)"
#: upper edges of the predicted-success bins of the calibration table (the first bin starts at 0, the last holds 1)
CALIBRATION_EDGES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)

MANIFEST_FORMAT = "normpos-grasp/simulate-run@1"
SCENE_FORMAT = "normpos-grasp/simulate-scene@1"
#: files of a finished run besides manifest.json and scenes/ (summary.json is written last)
RESULT_FILES = (
    "picks.csv",
    "success_by_part.png",
    "success_by_depth.png",
    "success_by_occlusion.png",
    "timing.json",
    "failures.html",
    "summary.json",
)
#: seconds a worker gets to exit after SIGTERM before it is killed
STOP_GRACE_S = 2.0


@dataclass(frozen=True)
class BatchResult:
    """Scenes of a batch in scene order."""

    config: SimulationConfig
    scenes: tuple[SceneResult, ...]

    @property
    def picks(self) -> list[PickRecord]:
        return [p for s in self.scenes for p in s.picks]


def _scene_task(args: tuple[SimulationConfig, int]) -> SceneResult:
    config, index = args
    return run_scene(config, index)


def run_batch(
    config: SimulationConfig,
    n_scenes: int,
    workers: int = 1,
    ray_address: str | None = None,
    progress: ProgressFn | None = None,
    done: Mapping[int, SceneResult] | None = None,
    on_scene: SceneFn | None = None,
) -> BatchResult:
    """Simulate scenes 0 .. n_scenes-1 of `config`. workers: local worker processes (spawned, single-threaded).
    ray_address: run scenes as Ray tasks on this cluster ('auto', 'local' for a new local cluster, or an
    address); needs the optional 'ray' package. progress(done, total) is called as scenes finish.
    done: scenes already finished (index -> result, e.g. `RunFolder.load_scenes()`); they are not run again.
    on_scene(result) is called in this process for every newly finished scene, in completion order.

    SIGINT / SIGTERM (in the main thread) cancel pending scenes, end the workers and raise `Interrupted`
    (what `on_scene` received is all that finished)."""
    if n_scenes < 1:
        raise InputError(f"n_scenes must be >= 1, got {n_scenes}")
    if workers < 1:
        raise InputError(f"workers must be >= 1, got {workers}")
    finished: dict[int, SceneResult] = {i: r for i, r in (done or {}).items() if 0 <= i < n_scenes}
    tasks = [(config, i) for i in range(n_scenes) if i not in finished]

    def finish(res: SceneResult) -> None:
        finished[res.scene] = res
        if on_scene is not None:
            on_scene(res)
        if progress is not None:
            progress(len(finished), n_scenes)

    if tasks:
        try:
            with signals_raise():
                if ray_address:
                    _run_ray(tasks, ray_address, finish)
                else:
                    _run_local(tasks, workers, finish)
        except Interrupted as exc:
            raise Interrupted(exc.signum, len(finished), n_scenes) from None
    results = sorted(finished.values(), key=lambda r: r.scene)
    return BatchResult(config, tuple(results))


def _run_local(tasks: list[tuple[SimulationConfig, int]], workers: int, finish: SceneFn) -> None:
    import multiprocessing

    # Scenes always run in fresh spawned processes with single-threaded BLAS: multi-threaded reductions
    # change the last bits of fits with the thread count, and no MuJoCo / EGL state is inherited.
    ctx = multiprocessing.get_context("spawn")
    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    os.environ.update(THREAD_ENV)
    pool = ProcessPoolExecutor(
        max_workers=min(workers, len(tasks)), mp_context=ctx, initializer=init_worker, initargs=(os.getpid(),)
    )
    try:
        with signals_deferred():  # the workers are spawned here (one per submit, up to max_workers)
            pending: set[Future[SceneResult]] = {pool.submit(_scene_task, t) for t in tasks}
        while pending:
            ready, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in ready:
                finish(fut.result())
    except BaseException:
        with signals_ignored():
            _stop_pool(pool)
        raise
    else:
        pool.shutdown(wait=True)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel what has not started and end every worker now: SIGTERM, then SIGKILL after STOP_GRACE_S."""
    procs = list((getattr(pool, "_processes", None) or {}).values())  # no public API lists the workers
    for p in procs:
        with contextlib.suppress(OSError, ValueError):
            p.terminate()
    for p in procs:
        with contextlib.suppress(OSError, ValueError, AssertionError):
            p.join(STOP_GRACE_S)
            if p.is_alive():
                p.kill()
                p.join(STOP_GRACE_S)
    pool.shutdown(wait=False, cancel_futures=True)
    # Wait for the pool's manager thread to finish closing its wake-up pipe: left running, it races the interpreter's
    # exit hook (concurrent.futures.process._python_exit writes to that pipe) into an OSError traceback on stderr
    # after the one-line message (CPython 3.11).
    manager = getattr(pool, "_executor_manager_thread", None)  # no public API exposes it
    if manager is not None:
        manager.join(STOP_GRACE_S)


def _run_ray(tasks: list[tuple[SimulationConfig, int]], address: str, finish: SceneFn) -> None:
    try:
        import ray
    except ImportError as exc:
        raise MissingDependency("ray", "scale", "simulate --ray") from exc
    started = False
    if not ray.is_initialized():
        try:
            if address == "local":
                ray.init(include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=address, log_to_driver=False)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise SimulationError(
                f"could not connect to the Ray cluster at {address!r}: {exc}; start one with `ray start --head` "
                "or use --ray local"
            ) from exc
        started = True
    pending: dict[Any, int] = {}
    try:
        remote = ray.remote(_scene_task).options(runtime_env={"env_vars": dict(THREAD_ENV)})
        pending = {remote.remote(t): t[1] for t in tasks}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                pending.pop(ref)
                finish(ray.get(ref))
    except BaseException:
        with signals_ignored():
            for ref in pending:  # the tasks of an interrupted batch do not run on
                try:
                    ray.cancel(ref, force=True)
                except Exception as exc:  # best effort: a task that finished or a cluster that is gone
                    logger.warning("could not cancel Ray task of scene %d: %s", pending[ref], exc)
        raise
    finally:
        if started:
            with signals_ignored():
                ray.shutdown()


# -- run folders -------------------------------------------------------------------------------------------
def run_parameters(config: SimulationConfig, n_scenes: int) -> dict[str, Any]:
    """Everything that changes a batch's results, as JSON-ready data: the whole config (cell as a resolved path
    and the SHA-256 of its file), the number of scenes and the package version. Worker counts and Ray are not
    parameters (results do not depend on them)."""
    params: dict[str, Any] = {"version": __version__, "scenes": int(n_scenes)}
    params.update(dataclasses.asdict(config))
    cell = Path(config.cell_path).resolve()
    params["cell_path"] = str(cell)
    params["cell_sha256"] = hashlib.sha256(cell.read_bytes()).hexdigest()
    return json.loads(json.dumps(params))  # tuples as lists, as they read back


def scene_to_json(result: SceneResult) -> dict[str, Any]:
    """Lossless JSON mapping of a scene (floats round-trip exactly; NaN / inf as JSON's NaN / Infinity)."""
    return {
        "format": SCENE_FORMAT,
        "scene": result.scene,
        "n_parts": result.n_parts,
        "cleared": result.cleared,
        "parts_left": result.parts_left,
        "picks": [dict(p.__dict__) for p in result.picks],
        "left": [dict(left.__dict__) for left in result.left],
    }


def scene_from_json(data: Any, source: str = "scene") -> SceneResult:
    """Inverse of `scene_to_json`; raises InputError naming `source` when the data is not such a scene."""
    fields = [f.name for f in dataclasses.fields(PickRecord)]
    try:
        if data.get("format") != SCENE_FORMAT:
            raise InputError(f"{source}: not a simulate scene file (format {data.get('format')!r})")
        picks = tuple(PickRecord(**{k: p[k] for k in fields if k in p}) for p in data["picks"])
        left = tuple(LeftPart(str(e["part"]), str(e["stage"]), str(e["detail"])) for e in data.get("left", ()))
        return SceneResult(
            int(data["scene"]), int(data["n_parts"]), bool(data["cleared"]), picks, int(data["parts_left"]), left
        )
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{source}: malformed simulate scene file ({type(exc).__name__}: {exc})") from None


class RunFolder:
    """The output folder of one `simulate` run: manifest.json, scenes/, and the results written at the end."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.manifest_path = self.path / "manifest.json"
        self.scenes_dir = self.path / "scenes"
        self.summary_path = self.path / "summary.json"

    @property
    def started(self) -> bool:
        """Whether a run was started here (its manifest exists)."""
        return self.manifest_path.is_file()

    @property
    def complete(self) -> bool:
        """Whether the run here finished (summary.json, written last, exists)."""
        return self.summary_path.is_file()

    def start(self, parameters: Mapping[str, Any]) -> None:
        """Create the folder and write the manifest (before any scene runs; a folder holding anything else but
        the manifest has one)."""
        self.path.mkdir(parents=True, exist_ok=True)
        manifest = {"format": MANIFEST_FORMAT, "parameters": dict(parameters)}
        atomic_write_text(self.manifest_path, json.dumps(manifest, indent=1) + "\n")
        self.scenes_dir.mkdir(exist_ok=True)

    def clear(self) -> None:
        """Remove an earlier run's manifest, scene files and results (other files in the folder are kept)."""
        for name in ("manifest.json", *RESULT_FILES):
            with contextlib.suppress(FileNotFoundError):
                (self.path / name).unlink()
        for folder in (self.scenes_dir, self.path / "failures"):
            if folder.is_dir():
                shutil.rmtree(folder)

    def parameters(self) -> dict[str, Any]:
        """The manifest's parameters; InputError when it is not a simulate manifest."""
        try:
            data = json.loads(self.manifest_path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(f"{self.manifest_path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
        if (
            not isinstance(data, dict)
            or data.get("format") != MANIFEST_FORMAT
            or not isinstance(data.get("parameters"), dict)
        ):
            raise InputError(f"{self.manifest_path}: not a simulate run manifest ({MANIFEST_FORMAT})")
        return dict(data["parameters"])

    def check_resume(self, parameters: Mapping[str, Any]) -> None:
        """InputError naming the differing parameters when the manifest's differ from `parameters`."""
        old = self.parameters()
        keys = sorted(set(old) | set(parameters))
        diff = [k for k in keys if old.get(k) != parameters.get(k)]
        if diff:
            shown = ", ".join(f"{k} {_short(old.get(k))} -> {_short(parameters.get(k))}" for k in diff[:4])
            more = f" and {len(diff) - 4} more" if len(diff) > 4 else ""
            raise InputError(
                f"--resume: the run in {self.path} was started with other parameters ({shown}{more}); "
                "repeat its options or choose another --out"
            )

    def scene_path(self, index: int) -> Path:
        return self.scenes_dir / f"scene_{index:06d}.json"

    def write_scene(self, result: SceneResult) -> None:
        """Write one finished scene atomically (a reader sees the whole file or none), after its failure pictures."""
        for name, png in result.pictures:
            path = self.path / name
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(path, png)
        text = json.dumps(scene_to_json(result), indent=None, separators=(",", ":")) + "\n"
        atomic_write_text(self.scene_path(result.scene), text)

    def load_scenes(self, n_scenes: int) -> dict[int, SceneResult]:
        """Finished scenes 0 .. n_scenes-1 (index -> result); leftovers of interrupted writes are removed."""
        out: dict[int, SceneResult] = {}
        if not self.scenes_dir.is_dir():
            return out
        for partial in self.scenes_dir.glob(".*.partial"):
            with contextlib.suppress(FileNotFoundError):
                partial.unlink()
        for index in range(n_scenes):
            path = self.scene_path(index)
            if not path.is_file():
                continue
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except json.JSONDecodeError as exc:
                raise InputError(f"{path}: not valid JSON ({exc.msg}); remove it to run the scene again") from None
            result = scene_from_json(data, str(path))
            if result.scene != index:
                raise InputError(f"{path}: holds scene {result.scene}, not {index}")
            out[index] = result
        return out


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def summarise(result: BatchResult) -> dict[str, Any]:
    """summary.json mapping: counts, success rate, failures by cause, per-part rates, scenes cleared."""
    picks = result.picks
    attempted = len(picks)
    succeeded = sum(1 for p in picks if p.success)
    causes = {c: sum(1 for p in picks if p.cause == c) for c in CAUSES}
    by_part: dict[str, dict[str, int]] = {}
    for p in picks:
        key = p.part or "(none)"
        entry = by_part.setdefault(key, {"attempted": 0, "succeeded": 0})
        entry["attempted"] += 1
        entry["succeeded"] += int(p.success)
    physics: dict[str, int] = {}
    for p in picks:
        if p.physics:
            physics[p.physics] = physics.get(p.physics, 0) + 1
    cfg = result.config
    return {
        "format": "normpos-grasp/simulate@1",
        "cell": Path(cfg.cell_path).name,
        "sensor": cfg.sensor,
        "seed": cfg.seed,
        "segmenter": cfg.segmenter,
        "scenes": len(result.scenes),
        "parts_total": sum(s.n_parts for s in result.scenes),
        "scenes_cleared": sum(1 for s in result.scenes if s.cleared),
        "parts_picked": succeeded,
        "parts_left_in_bin": sum(s.parts_left for s in result.scenes),
        "nudges": sum(p.nudges for p in picks),
        "nudge_collisions": sum(p.nudge_collisions for p in picks),
        "drags": sum(p.drags for p in picks),
        "picks_attempted": attempted,
        "picks_succeeded": succeeded,
        "success_rate": round(succeeded / attempted, 6) if attempted else 0.0,
        "failures_by_cause": causes,
        "physics_outcomes": dict(sorted(physics.items())),
        "by_part": dict(sorted(by_part.items())),
        "by_kind": held_by(picks, "kind", KINDS),
        "by_plan_pass": held_by(picks, "plan_pass", PLANNING_PASSES),
        "calibration": calibration(picks),
        "causes": cause_rows(result.scenes),
    }


def held_by(picks: Collection[PickRecord], field: str, order: tuple[str, ...]) -> dict[str, dict[str, Any]]:
    """Picks, held picks and held % for each value of the record's `field` ('kind' or 'plan_pass') in `order`, then
    NO_GRASP for the picks without a grasp ('' in the field); only values with picks. The picks add up to all picks
    and the held to all held. A value outside `order` is an error (a record this code did not write)."""
    counts: dict[str, list[int]] = {}
    for p in picks:
        value = str(getattr(p, field)) or NO_GRASP
        if value != NO_GRASP and value not in order:
            raise InputError(f"pick {p.scene}/{p.pick}: {field} {value!r} is not one of {order}")
        entry = counts.setdefault(value, [0, 0])
        entry[0] += 1
        entry[1] += int(p.success)
    return {
        k: {"picks": counts[k][0], "held": counts[k][1], "held_pct": round(100.0 * counts[k][1] / counts[k][0], 2)}
        for k in (*order, NO_GRASP)
        if k in counts
    }


def calibration(picks: Collection[PickRecord]) -> list[dict[str, Any]]:
    """Predicted against observed success of the grasps physics judged (a chosen grasp replayed in MuJoCo; picks
    without a physics outcome are left out), per predicted-success bin of CALIBRATION_EDGES (populated bins only,
    in increasing order): the bin's edges, picks, held, mean predicted success and observed held share."""
    bins: dict[int, list[float]] = {}
    for p in picks:
        if not p.physics or not math.isfinite(p.predicted_success):
            continue
        k = next((i for i, hi in enumerate(CALIBRATION_EDGES) if p.predicted_success < hi), len(CALIBRATION_EDGES) - 1)
        entry = bins.setdefault(k, [0.0, 0.0, 0.0])
        entry[0] += 1
        entry[1] += float(p.success)
        entry[2] += float(p.predicted_success)
    out = []
    for k in sorted(bins):
        n, held, predicted = bins[k]
        out.append(
            {
                "low": CALIBRATION_EDGES[k - 1] if k > 0 else 0.0,
                "high": CALIBRATION_EDGES[k],
                "picks": int(n),
                "held": int(held),
                "predicted": round(predicted / n, 4),
                "observed": round(held / n, 4),
            }
        )
    return out


def format_breakdown(summary: Mapping[str, Any]) -> str:
    """The per-kind held table and the calibration table of a summary as fixed-width text lines (the console's)."""
    lines = ["picks by grasp kind (what produced the chosen grasp; no grasp: give-ups):"]
    lines.append(f"{'kind':<12} {'picks':>6} {'held':>6} {'held %':>7}")
    for kind, r in summary["by_kind"].items():
        lines.append(f"{kind:<12} {r['picks']:>6} {r['held']:>6} {r['held_pct']:>7.1f}")
    passes = ", ".join(f"{k} {r['held']}/{r['picks']}" for k, r in summary["by_plan_pass"].items() if k != NO_GRASP)
    lines.append(f"by planner pass: {passes or 'none'}")
    rows = summary["calibration"]
    if not rows:
        lines.append("calibration: no grasp was judged in physics")
        return "\n".join(lines)
    lines.append("calibration (grasps judged in physics, by predicted success):")
    lines.append(f"{'bin':<10} {'picks':>6} {'held':>6} {'predicted':>10} {'observed':>9}")
    for r in rows:
        edges = f"{r['low']:.1f}-{r['high']:.1f}"
        lines.append(f"{edges:<10} {r['picks']:>6} {r['held']:>6} {r['predicted']:>10.3f} {r['observed']:>9.3f}")
    return "\n".join(lines)


def _csv_value(value: Any) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return "" if math.isnan(value) else ("inf" if math.isinf(value) else f"{value:.6f}")
    return str(value)


def write_results(result: BatchResult, out_dir: str | Path, timing: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write picks.csv, the plots, timing.json (when given) and, last, summary.json to `out_dir` (each file
    atomically); returns the summary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for p in result.picks:
        row = p.row()
        writer.writerow([_csv_value(row[c]) for c in CSV_COLUMNS])
    atomic_write_text(out / "picks.csv", buf.getvalue())
    from normpos_grasp.simulate.plots import write_plots

    write_plots(result.picks, out)
    if timing is not None:
        atomic_write_text(out / "timing.json", json.dumps(timing, indent=1) + "\n")
    summary = summarise(result)
    atomic_write_text(out / "failures.html", failures_page(summary))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1, sort_keys=False) + "\n")
    return summary


def failures_page(summary: Mapping[str, Any]) -> str:
    """failures.html: the cause table (stage, detail, failed picks, parts left) with the first picture of each."""
    import html

    rows = []
    for r in summary["causes"]:
        pic = html.escape(str(r["picture"]))
        img = f'<a href="{pic}"><img src="{pic}" width="320"></a>' if pic else "-"
        rows.append(
            f"<tr><td>{html.escape(r['stage'])}</td><td>{html.escape(r['detail'])}</td>"
            f"<td>{r['failed_picks']}</td><td>{r['parts_left']}</td><td>{img}</td></tr>"
        )
    held = f"{summary['picks_succeeded']} / {summary['picks_attempted']} picks held"
    cleared = f"{summary['scenes_cleared']} / {summary['scenes']} bins cleared"
    kinds = "".join(
        f"<tr><td>{html.escape(k)}</td><td>{r['picks']}</td><td>{r['held']}</td><td>{r['held_pct']:.1f}</td></tr>"
        for k, r in summary["by_kind"].items()
    )
    bins = "".join(
        f"<tr><td>{r['low']:.1f}-{r['high']:.1f}</td><td>{r['picks']}</td><td>{r['held']}</td>"
        f"<td>{r['predicted']:.3f}</td><td>{r['observed']:.3f}</td></tr>"
        for r in summary["calibration"]
    )
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>simulate: failures by cause</title></head><body>"
        f"<h1>Failures by cause</h1><p>{held}; {cleared}; {summary['parts_left_in_bin']} parts left in bins</p>"
        "<table border='1' cellpadding='4'><tr><th>stage</th><th>detail</th><th>failed picks</th>"
        "<th>parts left</th><th>picture</th></tr>" + "".join(rows) + "</table>"
        "<h2>Picks by grasp kind</h2><table border='1' cellpadding='4'><tr><th>kind</th><th>picks</th><th>held</th>"
        "<th>held %</th></tr>" + kinds + "</table>"
        "<h2>Predicted against observed success (grasps judged in physics)</h2><table border='1' cellpadding='4'>"
        "<tr><th>predicted bin</th><th>picks</th><th>held</th><th>mean predicted</th><th>observed</th></tr>"
        + bins
        + "</table></body></html>\n"
    )


def timing_summary(result: BatchResult, wall_s: float, resumed: Collection[int] = ()) -> dict[str, Any]:
    """Wall-clock figures of a run (not deterministic, kept apart from summary.json). resumed: indices of the
    scenes taken from an earlier, interrupted run; the figures count only the scenes this run simulated."""
    scenes = result.scenes
    skip = set(resumed)
    ran = [s for s in scenes if s.scene not in skip]
    picks = [p for s in ran for p in s.picks]
    physics_ms = [p.physics_ms for p in picks if p.physics]
    pipeline_ms = [p.pipeline_ms for p in picks]
    return {
        "wall_s": round(wall_s, 3),
        "scenes_run": len(ran),
        "scenes_resumed": len(scenes) - len(ran),
        "picks": len(picks),
        "picks_per_minute": round(60.0 * len(picks) / wall_s, 3) if wall_s > 0 else 0.0,
        "physics_validations": len(physics_ms),
        "physics_ms_median": round(float(np.median(physics_ms)), 3) if physics_ms else 0.0,
        "pipeline_ms_median": round(float(np.median(pipeline_ms)), 3) if pipeline_ms else 0.0,
        "cpu_count": os.cpu_count(),
    }
