"""Planner records: `Target` (an object to pick), `Evaluation` (the verdict on one grasp candidate), `Waypoint`,
`Trajectory` and `PickPlan` (the result of `planning.plan_pick`, with its plan.json mapping)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.kinds import PlanStatus
from normpos_grasp.records.tool import ToolModel
from normpos_grasp.typing import FloatArray

PLAN_FORMAT = "normpos-grasp/plan@1"


@dataclass(frozen=True, eq=False)
class Target:
    """An object to pick: `name` (world element name), its mesh's lowest point below... `world_from_object`,
    `template` mesh (for the held object), `height_m` (world z of its centre), mass_kg; measured_points: for an
    object no template explains (its mesh a box around them), its measured surface (N, 3) world, m: what a grasp
    must hold on."""

    name: str
    world_from_object: FloatArray
    mesh: object
    height_m: float
    mass_kg: float = 0.1
    instance_id: int = 0
    template: str = ""
    measured_points: FloatArray | None = None


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Verdict on one candidate: feasible or the reason (and the pose it failed at, one of POSE_NAMES);
    world_from_tcp (5, 4, 4) and q (5, 6) rad at the five poses when IK succeeded; branch: IK branch index;
    score: ranking score (higher is better). POSE_NAMES: `planning.evaluate.POSE_NAMES`."""

    candidate: GraspCandidate
    feasible: bool
    reason: str = ""
    pose: str = ""
    world_from_tcp: FloatArray | None = None
    q: FloatArray | None = None
    branch: int = -1
    score: float = -np.inf
    prior: float = 0.0

    @classmethod
    def rejected(
        cls, candidate: GraspCandidate, reason: str, pose: str, world_from_tcp: FloatArray | None, prior: float = 0.0
    ) -> Evaluation:
        """`Evaluation(candidate, False, reason, pose, world_from_tcp, prior=prior)` (every other field its default),
        built without the frozen dataclass's per-field `object.__setattr__`: about 0.6 us instead of 2.6, for the
        evaluator's ~1,400 rejected candidates per 10-part bin."""
        ev = object.__new__(cls)
        state = dict(_EVALUATION_DEFAULTS, candidate=candidate, reason=reason, pose=pose, world_from_tcp=world_from_tcp)
        state["prior"] = prior
        object.__setattr__(ev, "__dict__", state)
        return ev


#: every field of Evaluation in order with its default (candidate None, feasible False): what `Evaluation.rejected`
#: starts from
_EVALUATION_DEFAULTS: dict[str, Any] = {f.name: f.default for f in fields(Evaluation)}
_EVALUATION_DEFAULTS.update(candidate=None, feasible=False)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Time-stamped joint samples: t (M,) s from 0, q (M, 6) rad, qd (M, 6) rad/s."""

    t: FloatArray
    q: FloatArray
    qd: FloatArray

    @property
    def duration_s(self) -> float:
        return float(self.t[-1]) if len(self.t) else 0.0


@dataclass(frozen=True, eq=False)
class Waypoint:
    """A named configuration: q (6,) rad and the TCP pose world_from_tcp (4, 4) it reaches."""

    name: str
    q: FloatArray
    world_from_tcp: FloatArray


@dataclass(frozen=True, eq=False)
class PickPlan:
    """Result of `plan_pick`. status: 'ok' or 'no_feasible_grasp'. chosen: the evaluation of the grasp taken.
    counts: rejection counts by reason over all candidates. timing_ms: stage times.
    cell: the cell it was planned in ({name, path, sha256} of the cell file; empty for a cell built in memory):
    `execute` judges the plan against that cell when no --cell is given.
    bin: the bin the part is taken from and bins_empty: the bins this frame showed no part in, in a cell with
    several bins (plan.json then carries "bin" and "bins_empty"; '' and () in a one-bin cell).
    planning_pass: the planning pass whose candidates gave the chosen grasp ('first': as synthesised; 'turned': a
    dual-tool flange's copies turned about the approach axis; 'leaned': copies leaned away from the cell's boxes;
    `planning.plan.PLANNING_PASSES`), '' for a plan with no grasp. uncovered_voxels: clutter voxels the planner
    built from surfaces no instance covers (`measure.uncovered`: what the segmenter missed; plan.json carries
    "uncovered_voxels" when there are any): a plan with nothing to pick and uncovered voxels did not find the bin
    empty."""

    status: PlanStatus
    robot: str
    world_from_base: FloatArray
    tool: ToolModel
    targets: tuple[Target, ...]
    chosen: Evaluation | None
    waypoints: tuple[Waypoint, ...]
    trajectory: Trajectory | None
    evaluations: tuple[Evaluation, ...]
    counts: dict[str, int]
    n_feasible: int
    timing_ms: dict[str, float] = field(default_factory=dict)
    place: str = ""
    cell: dict[str, str] = field(default_factory=dict)
    bin: str = ""
    bins_empty: tuple[str, ...] = ()
    planning_pass: str = ""
    uncovered_voxels: int = 0

    def to_json(self) -> dict[str, Any]:
        """The documented plan.json mapping (docs/grasping.md)."""
        opening = self.chosen.candidate.opening_m if self.chosen is not None else 0.0
        rejected = {k: v for k, v in sorted(self.counts.items()) if k != "not_evaluated"}
        out: dict[str, Any] = {
            "format": PLAN_FORMAT,
            "status": self.status,
            "robot": self.robot,
            "world_from_base": np.asarray(self.world_from_base).tolist(),
            "tool": self.tool.to_json(opening),
            "cell": dict(self.cell),
            "target": None,
            "grasp": None,
            "joint_waypoints": [
                {"name": w.name, "q": [float(v) for v in w.q], "world_from_tcp": np.asarray(w.world_from_tcp).tolist()}
                for w in self.waypoints
            ],
            "trajectory": None,
            "candidates": {
                "total": len(self.evaluations),
                "evaluated": sum(1 for e in self.evaluations if e.reason != "not_evaluated"),
                "feasible": self.n_feasible,
                "not_evaluated": int(self.counts.get("not_evaluated", 0)),
                "rejected_by_reason": rejected,
            },
            "timing_ms": {k: round(float(v), 3) for k, v in self.timing_ms.items()},
        }
        if self.bin or self.bins_empty:
            out["bin"] = self.bin
            out["bins_empty"] = list(self.bins_empty)
        if self.uncovered_voxels:
            out["uncovered_voxels"] = int(self.uncovered_voxels)
        if self.chosen is not None:
            c = self.chosen.candidate
            t = self.targets[c.target]
            out["target"] = {
                "instance": int(t.instance_id),
                "name": t.name,
                "template": t.template,
                "world_from_object": np.asarray(t.world_from_object).tolist(),
            }
            out["grasp"] = {
                "id": c.grasp_id,
                "scheme": c.scheme,
                "source": c.source,
                "world_from_tcp": np.asarray(c.world_from_tcp).tolist(),
                "opening_m": float(c.opening_m),
                "quality": float(c.quality),
                "score": float(self.chosen.score),
                "place": self.place,
            }
        if self.trajectory is not None:
            out["trajectory"] = {
                "dt_s": float(np.median(np.diff(self.trajectory.t))) if len(self.trajectory.t) > 1 else 0.0,
                "duration_s": self.trajectory.duration_s,
                "samples": [
                    {"t": round(float(t), 6), "q": [round(float(v), 9) for v in q]}
                    for t, q in zip(self.trajectory.t, self.trajectory.q, strict=True)
                ],
            }
        return out

    def save(self, path: str | Path) -> None:
        """Write plan.json."""
        Path(path).write_text(json.dumps(self.to_json(), indent=1), encoding="utf-8")
