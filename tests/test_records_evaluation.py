"""`Evaluation.rejected`, the evaluator's fast constructor of a rejected candidate's verdict, builds exactly what the
dataclass constructor builds: every field, in order, with the same values (a field added to `Evaluation` later gets
its default here too, or this fails)."""

from __future__ import annotations

from dataclasses import fields

import numpy as np

from normpos_grasp.records.grasp import GraspCandidate
from normpos_grasp.records.plan import Evaluation


def test_rejected_is_the_dataclass_built_with_feasible_false() -> None:
    cand = GraspCandidate(2, "box", "g7", "template", "parallel", np.eye(4), 0.05, 0.1, 0.08, 0.9)
    poses = np.arange(80.0).reshape(5, 4, 4)
    for prior in (0.0, np.float64(1.25)):
        fast = Evaluation.rejected(cand, "collision_cell", "pre_grasp", poses, prior=prior)
        slow = Evaluation(cand, False, "collision_cell", "pre_grasp", poses, prior=prior)
        assert list(vars(fast)) == [f.name for f in fields(Evaluation)]
        for f in fields(Evaluation):
            a, b = getattr(fast, f.name), getattr(slow, f.name)
            assert a is b or (type(a) is type(b) and a == b), f.name
    plain = Evaluation.rejected(cand, "not_evaluated", "", None)
    assert not plain.feasible and plain.q is None and plain.branch == -1 and plain.score == -np.inf
    assert plain.prior == 0.0 and plain.world_from_tcp is None
