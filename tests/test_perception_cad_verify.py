"""The cad detector's verification against the whole scene: a small template posed on part of a larger part's
surface is refuted by the surface going on past its silhouette; the right, larger template is not."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.camera.render import render
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.measure.measure import backproject_depth
from normpos_grasp.perception.cad_detector import CadDetector, RegionOfInterest, _dilate
from normpos_grasp.records.template import Template
from normpos_grasp.sim.parts import box_symmetry
from normpos_grasp.templates.prepared import prepare

K = np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]])


def _box(name: str, ext: tuple[float, float, float]) -> Template:
    e = np.array(ext)
    return Template(name=name, label=name, mesh=trimesh.creation.box(extents=e), symmetry=box_symmetry(e))


@pytest.fixture(scope="module")
def block_scene():  # type: ignore[no-untyped-def]
    """A 60 x 60 x 20 mm block on the floor seen from 0.7 m, 25 degrees off vertical, 1.5 mm depth noise."""
    tilt = np.deg2rad(25.0)
    wfc = np.eye(4)
    look = np.diag([1.0, -1.0, -1.0])  # looking down: camera z = world -z
    rx = np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]])
    wfc[:3, :3] = rx @ look
    wfc[:3, 3] = -0.7 * wfc[:3, 2]  # 0.7 m from the block's centre along the viewing axis
    cam = Camera(K, 640, 480, world_from_camera=wfc)
    big = _box("block60", (0.06, 0.06, 0.02))
    truth = np.eye(4)
    truth[2, 3] = 0.01  # resting on the floor (z = 0)
    floor = trimesh.creation.box(extents=[0.6, 0.6, 0.01])
    floor_pose = np.eye(4)
    floor_pose[2, 3] = -0.005
    cfw = invert_pose(wfc)
    rend = render(cam, [(big.mesh, cfw @ truth), (floor, cfw @ floor_pose)])
    rng = np.random.default_rng(7)
    depth = rend.depth_m + rng.normal(0.0, 0.0015, rend.depth_m.shape) * (rend.depth_m > 0)
    frame = RGBDFrame(np.zeros((480, 640, 3), np.uint8), depth, cam)
    box = np.eye(4)
    box[2, 3] = 0.12
    roi = RegionOfInterest(np.array([0.0, 0.0, 1.0, 0.0]), box, np.array([0.4, 0.4, 0.24]))
    return frame, big, cfw, truth, roi


def _judge(frame, roi, template, cfo):  # type: ignore[no-untyped-def]
    det = CadDetector([template], roi)
    depth = np.ascontiguousarray(frame.depth_m, dtype=np.float64)
    pmap = backproject_depth(frame.camera, depth)
    det._camera_k = K
    det._depth = depth
    in_roi = det._roi_mask(frame, pmap, roi)
    others = np.zeros(in_roi.shape, dtype=bool)
    near = _dilate(in_roi.reshape(depth.shape), det.options.off_roi_margin_px).reshape(-1)  # as the detector does
    return det._contradiction(pmap, in_roi, others, prepare(template), cfo, 1.0, near)


def test_a_small_template_on_a_larger_surface_is_contradicted(block_scene) -> None:  # type: ignore[no-untyped-def]
    frame, big, cfw, truth, roi = block_scene
    opts = CadDetector([big]).options
    cont, off = _judge(frame, roi, big, cfw @ truth)
    assert cont < 0.5 * opts.max_continuation and off < 0.5 * opts.max_off_roi  # the right block: nothing goes on
    small = _box("block20", (0.02, 0.02, 0.02))
    on_top = np.eye(4)
    on_top[2, 3] = 0.01  # its top face in the block's top face: explains it, its sides hidden inside the block
    cont, _ = _judge(frame, roi, small, cfw @ on_top)
    assert cont > 3 * opts.max_continuation  # the block's top goes on all round the small one's silhouette


def test_a_template_on_the_bare_floor_is_supported_outside_the_roi(block_scene) -> None:  # type: ignore[no-untyped-def]
    frame, big, cfw, _, roi = block_scene
    plate = _box("plate30", (0.03, 0.03, 0.003))
    beside = np.eye(4)
    beside[:3, 3] = [0.09, 0.0, 0.0015]  # on the floor next to the block, where there is no part
    _, off = _judge(frame, roi, plate, cfw @ beside)
    assert off > CadDetector([big]).options.max_off_roi
