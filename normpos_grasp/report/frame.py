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


def frame_overlay(result: FrameResult) -> UInt8Array:
    """The frame's RGB with instance masks, labels, accepted template outlines and the chosen grasp."""
    outlines = []
    for k, fit in enumerate(result.fits):
        if not fit.accepted:
            continue
        mesh = fit.template.mesh
        verts = np.asarray(mesh.vertices, dtype=np.float64) * fit.scale
        verts = verts @ fit.world_from_object[:3, :3].T + fit.world_from_object[:3, 3]
        outlines.append(
            OutlineItem(verts, np.asarray(mesh.faces), f"{fit.template.name} {fit.score:.2f}", palette_color(k))
        )
    grasp, opening = None, 0.0
    plan = result.plan
    if plan is not None and plan.chosen is not None:
        grasp, opening = plan.chosen.candidate.world_from_tcp, plan.chosen.candidate.opening_m
    return draw_overlay(result.frame.rgb, result.frame.camera, result.instances, outlines, grasp, opening)


def frame_twin(result: FrameResult, cell: CellConfig, arm_q: FloatArray | None = None) -> TwinScene:
    """The measured scene rebuilt in 3D: cell boxes, measured points, fitted templates, arm and gripper.

    The arm is drawn at the chosen grasp (or at `arm_q` when given, or at home when there is no plan).
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
