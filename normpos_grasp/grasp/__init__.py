"""Grasp candidates per object shape: template-annotated pick frames and automatic synthesis."""

from normpos_grasp.grasp.candidates import (
    CandidateOptions,
    GraspCandidate,
    candidates_for_object,
    expand_annotation,
    primitive_template,
    vertical_prism_grasps,
)
from normpos_grasp.grasp.synthesis import SynthesisOptions, synthesize, tcp_frame

__all__ = [
    "CandidateOptions",
    "GraspCandidate",
    "SynthesisOptions",
    "candidates_for_object",
    "expand_annotation",
    "primitive_template",
    "synthesize",
    "tcp_frame",
    "vertical_prism_grasps",
]
