"""Pictures and 3D twins of a processed frame (`pipeline.FrameResult`) in its cell."""

from __future__ import annotations

import numpy as np

from normpos_grasp.cell.config import CellConfig
from normpos_grasp.pipeline import FrameResult
from normpos_grasp.report.overlay import OutlineItem, draw_overlay
from normpos_grasp.report.scene3d import TwinScene, palette_color
from normpos_grasp.typing import FloatArray, UInt8Array

CELL_GREY = (175, 178, 185)
ARM_GREY = (90, 95, 105)
TOOL_BLUE = (40, 90, 200)
FEASIBLE_GREEN = (20, 200, 60)
# rejection reason (prefix) -> marker colour; reasons not listed get OTHER_REASON
REASON_COLORS: dict[str, tuple[int, int, int]] = {
    "approach_angle": (150, 150, 150),
    "stroke": (255, 150, 0),
    "workspace": (120, 60, 20),
    "ik": (200, 0, 0),
    "joint_limits": (255, 80, 160),
    "collision_cell": (130, 0, 200),
    "collision_object": (255, 220, 0),
    "collision_clutter": (0, 190, 220),
    "collision_self": (90, 40, 160),
    "payload": (0, 0, 0),
    "path": (255, 0, 255),
    "not_evaluated": (210, 210, 210),
}
OTHER_REASON = (100, 100, 100)


def frame_overlay(result: FrameResult) -> UInt8Array:
    """The frame's RGB with instance masks, labels, accepted template outlines and the chosen grasp."""
    outlines = []
    for k, fit in enumerate(result.fits):
        if not fit.accepted:
            continue
        mesh = fit.template.mesh
        verts = np.asarray(mesh.vertices, dtype=np.float64) * fit.scale
        pose = fit.frame_from_object  # world or camera: the frame draw_overlay reads for this camera
        verts = verts @ pose[:3, :3].T + pose[:3, 3]
        outlines.append(
            OutlineItem(verts, np.asarray(mesh.faces), f"{fit.template.name} {fit.score:.2f}", palette_color(k))
        )
    grasp, opening = None, 0.0
    plan = result.plan
    if plan is not None and plan.chosen is not None:
        grasp, opening = plan.chosen.candidate.world_from_tcp, plan.chosen.candidate.opening_m
    return draw_overlay(result.frame.rgb, result.frame.camera, result.instances, outlines, grasp, opening)


def reason_color(reason: str) -> tuple[int, int, int]:
    """Marker colour of a rejection reason ('' or 'feasible': green); 'collision_cell_x' matches 'collision_cell'."""
    if reason in ("", "feasible"):
        return FEASIBLE_GREEN
    for key in sorted(REASON_COLORS, key=len, reverse=True):
        if reason == key or reason.startswith((key + "_", key + ":")):
            return REASON_COLORS[key]
    return OTHER_REASON


def add_candidate_markers(
    scene: TwinScene, result: FrameResult, size_m: float = 0.006, max_per_group: int = 400
) -> dict[str, int]:
    """Add the plan's grasp candidates as small octahedra at their TCP positions, one mesh per verdict
    ('candidates/feasible', 'candidates/<reason>'), coloured by `reason_color`. Each group is thinned evenly to
    `max_per_group` markers. Returns verdict -> number of candidates (before thinning)."""
    import trimesh

    plan = result.plan
    if plan is None or not plan.evaluations:
        return {}
    groups: dict[str, list[FloatArray]] = {}
    for ev in plan.evaluations:
        key = "feasible" if ev.feasible else (ev.reason or "rejected")
        groups.setdefault(key, []).append(np.asarray(ev.candidate.world_from_tcp, dtype=np.float64)[:3, 3])
    unit = trimesh.creation.icosphere(subdivisions=0, radius=size_m)
    verts0, faces0 = np.asarray(unit.vertices), np.asarray(unit.faces)
    counts: dict[str, int] = {}
    for key, positions in sorted(groups.items()):
        counts[key] = len(positions)
        pts = np.asarray(positions)
        if len(pts) > max_per_group:
            pts = pts[np.linspace(0, len(pts) - 1, max_per_group).round().astype(int)]
        verts = (verts0[None] + pts[:, None]).reshape(-1, 3)
        faces = (faces0[None] + (np.arange(len(pts)) * len(verts0))[:, None, None]).reshape(-1, 3)
        scene.add_mesh(f"candidates/{key}", trimesh.Trimesh(verts, faces, process=False), reason_color(key))
    return counts


def frame_twin(
    result: FrameResult, cell: CellConfig, arm_q: FloatArray | None = None, candidates: bool = False
) -> TwinScene:
    """The measured scene rebuilt in 3D: cell boxes, measured points, fitted templates, arm and gripper.

    The arm is drawn at the chosen grasp (or at `arm_q` when given, or at home when there is no plan). With
    `candidates`, the plan's grasp candidates are added as markers (`add_candidate_markers`).
    """
    from normpos_grasp.kinematics.robot import Robot

    scene = TwinScene()
    for box in cell.static_boxes:
        scene.add_box(box.name, box.world_from_box, box.size, CELL_GREY, 0.35 if box.name.startswith("bin") else 1.0)
    for k, np_ in enumerate(result.normpositions):
        scene.add_points(f"measured/{np_.instance_id}", np_.points, palette_color(k))
    for k, fit in enumerate(result.fits):
        if fit.accepted:
            mesh = fit.template.mesh.copy()
            mesh.apply_scale(fit.scale)
            scene.add_posed_mesh(f"fit/{fit.template.name}/{k}", mesh, fit.world_from_object, palette_color(k), 0.55)
    plan = result.plan
    q = arm_q
    if q is None and plan is not None and plan.chosen is not None and plan.chosen.q is not None:
        q = plan.chosen.q[2]  # the grasp pose of the five
    if q is None:
        q = np.asarray(cell.home_q, dtype=np.float64)
    robot = Robot.load(cell.robot_model)
    base_from_link = robot.link_poses(q)
    for i, shape in enumerate(robot.collision_geometry):
        pose = cell.world_from_base @ base_from_link[shape.link] @ shape.link_from_shape
        _add_shape(scene, f"arm/{shape.link}/{i}", shape.kind, shape.size, pose, ARM_GREY)
    world_from_tcp = cell.world_from_base @ robot.fk(q) @ cell.tool.flange_from_tcp
    opening = plan.chosen.candidate.opening_m if plan is not None and plan.chosen is not None else cell.tool.stroke_m
    for tool_shape, tcp_from_shape in cell.tool.posed_shapes(opening):
        pose = world_from_tcp @ tcp_from_shape
        _add_shape(scene, f"tool/{tool_shape.name}", tool_shape.kind, tool_shape.size, pose, TOOL_BLUE)
    scene.add_axes("tcp", world_from_tcp)
    if candidates:
        add_candidate_markers(scene, result)
    return scene


def _add_shape(
    scene: TwinScene, name: str, kind: str, size: tuple[float, ...], pose: FloatArray, color: tuple[int, int, int]
) -> None:
    import trimesh

    if kind == "box":
        scene.add_box(name, pose, np.asarray(size), color)
    elif kind == "capsule":
        scene.add_capsule(name, pose, size[0], size[1], color)
    elif kind == "cylinder":
        scene.add_posed_mesh(name, trimesh.creation.cylinder(radius=size[0], height=size[1], sections=16), pose, color)
    elif kind == "sphere":
        scene.add_posed_mesh(name, trimesh.creation.icosphere(subdivisions=2, radius=size[0]), pose, color)
