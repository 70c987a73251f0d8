"""Batches of simulated scenes: local processes (default) or Ray tasks, the per-pick CSV and summary.json.

Scenes are independent and seeded from (config.seed, scene index), so the results do not depend on the number
of workers or on Ray: records are sorted by (scene, pick) before they are written, and the written files hold
no wall-clock times (those go to timing.json), so two runs with the same seeds give byte-identical
picks.csv and summary.json.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.errors import InputError, MissingDependency, SimulationError
from normpos_grasp.simulate.episode import CAUSES, PickRecord, SceneResult, SimulationConfig, run_scene

logger = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]

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
)


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
) -> BatchResult:
    """Simulate scenes 0 .. n_scenes-1 of `config`. workers: local worker processes (spawned, single-threaded).
    ray_address: run scenes as Ray tasks on this cluster ('auto', 'local' for a new local cluster, or an
    address); needs the optional 'ray' package. progress(done, total) is called as scenes finish."""
    if n_scenes < 1:
        raise InputError(f"n_scenes must be >= 1, got {n_scenes}")
    if workers < 1:
        raise InputError(f"workers must be >= 1, got {workers}")
    tasks = [(config, i) for i in range(n_scenes)]
    results: list[SceneResult] = []
    if ray_address:
        results = _run_ray(tasks, ray_address, progress)
    else:
        import multiprocessing

        # Scenes always run in fresh spawned processes with single-threaded BLAS: multi-threaded reductions
        # change the last bits of fits with the thread count, and no MuJoCo / EGL state is inherited.
        ctx = multiprocessing.get_context("spawn")
        saved = {k: os.environ.get(k) for k in THREAD_ENV}
        os.environ.update(THREAD_ENV)
        try:
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
                for k, res in enumerate(pool.map(_scene_task, tasks)):
                    results.append(res)
                    if progress is not None:
                        progress(k + 1, n_scenes)
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
    results.sort(key=lambda r: r.scene)
    return BatchResult(config, tuple(results))


def _run_ray(tasks: list[tuple[SimulationConfig, int]], address: str, progress: ProgressFn | None) -> list[SceneResult]:
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
    try:
        remote = ray.remote(_scene_task).options(runtime_env={"env_vars": dict(THREAD_ENV)})
        pending = {remote.remote(t): t[1] for t in tasks}
        out: list[SceneResult] = []
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                out.append(ray.get(ref))
                pending.pop(ref)
            if progress is not None:
                progress(len(out), len(tasks))
        return out
    finally:
        if started:
            ray.shutdown()


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
        "picks_attempted": attempted,
        "picks_succeeded": succeeded,
        "success_rate": round(succeeded / attempted, 6) if attempted else 0.0,
        "failures_by_cause": causes,
        "physics_outcomes": dict(sorted(physics.items())),
        "by_part": dict(sorted(by_part.items())),
    }


def _csv_value(value: Any) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return "" if math.isnan(value) else ("inf" if math.isinf(value) else f"{value:.6f}")
    return str(value)


def write_results(result: BatchResult, out_dir: str | Path, timing: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write picks.csv, summary.json, timing.json (when given) and the plots to `out_dir`; returns the summary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "picks.csv").open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(CSV_COLUMNS)
        for p in result.picks:
            row = p.row()
            writer.writerow([_csv_value(row[c]) for c in CSV_COLUMNS])
    summary = summarise(result)
    (out / "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=False) + "\n", encoding="utf-8")
    if timing is not None:
        (out / "timing.json").write_text(json.dumps(timing, indent=1) + "\n", encoding="utf-8")
    from normpos_grasp.simulate.plots import write_plots

    write_plots(result.picks, out)
    return summary


def timing_summary(result: BatchResult, wall_s: float) -> dict[str, Any]:
    """Wall-clock figures of a run (not deterministic, kept apart from summary.json)."""
    picks = result.picks
    physics_ms = [p.physics_ms for p in picks if p.physics]
    pipeline_ms = [p.pipeline_ms for p in picks]
    return {
        "wall_s": round(wall_s, 3),
        "picks": len(picks),
        "picks_per_minute": round(60.0 * len(picks) / wall_s, 3) if wall_s > 0 else 0.0,
        "physics_validations": len(physics_ms),
        "physics_ms_median": round(float(np.median(physics_ms)), 3) if physics_ms else 0.0,
        "pipeline_ms_median": round(float(np.median(pipeline_ms)), 3) if pipeline_ms else 0.0,
        "cpu_count": os.cpu_count(),
    }
