"""`GraspCandidate`: one way to pick one object, in the world frame (grasp synthesis in, planner out)."""

from __future__ import annotations

from dataclasses import dataclass

from normpos_grasp.typing import FloatArray


@dataclass(frozen=True, eq=False)
class GraspCandidate:
    """One way to pick one object.

    target: index of the object in the planner's target list; template: its template name.
    grasp_id: annotation id (or synthesis id); source: 'annotated' or 'synthesized'; scheme: 'parallel' or
    'suction'; world_from_tcp (4, 4); opening_m: jaw opening before closing, m; approach_m / retreat_m: straight
    line lengths, m; quality in [0, 1] (geometry of the grasp); priority: template priority (higher first).
    """

    target: int
    template: str
    grasp_id: str
    source: str
    scheme: str
    world_from_tcp: FloatArray
    opening_m: float
    approach_m: float
    retreat_m: float
    quality: float
    priority: float = 0.0
