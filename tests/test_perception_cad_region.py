"""The cad detector's region evidence: thin parts kept in the ROI, raw vote peaks ranked on depth, poses that sink
into the support plane refused, plates slid and turned back onto their outline."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.camera.render import render
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.measure.measure import backproject_depth
from normpos_grasp.perception.cad_detector import CadDetector, CadOptions, RegionOfInterest
from normpos_grasp.records.template import Template
from normpos_grasp.sim.parts import box_symmetry, default_part_library
from normpos_grasp.templates import ppf
from normpos_grasp.templates.prepared import prepare

K = np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]])


def _plate() -> Template:
    ext = np.array([0.05, 0.05, 0.003])
    return Template(name="plate50", label="plate50", mesh=trimesh.creation.box(extents=ext), symmetry=box_symmetry(ext))


@pytest.fixture(scope="module")
def floor_scene():  # type: ignore[no-untyped-def]
    """A 3 mm plate on the floor seen from 0.8 m straight above, D435-like noise (2 mm RMS)."""
    wfc = np.eye(4)
    wfc[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking down: camera z = world -z
    wfc[2, 3] = 0.8
    cam = Camera(K, 640, 480, world_from_camera=wfc)
    plate = _plate()
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("z", 20, degrees=True).as_matrix()
    truth[:3, 3] = [0.01, -0.02, 0.0015]  # resting on the floor (z = 0)
    floor = trimesh.creation.box(extents=[0.5, 0.5, 0.01])
    floor_pose = np.eye(4)
    floor_pose[2, 3] = -0.005
    cfw = invert_pose(wfc)
    rend = render(cam, [(plate.mesh, cfw @ truth), (floor, cfw @ floor_pose)])
    rng = np.random.default_rng(5)
    depth = rend.depth_m + rng.normal(0.0, 0.002, rend.depth_m.shape) * (rend.depth_m > 0)
    frame = RGBDFrame(np.zeros((480, 640, 3), np.uint8), depth, cam)
    box = np.eye(4)
    box[2, 3] = 0.12
    roi = RegionOfInterest(np.array([0.0, 0.0, 1.0, 0.0]), box, np.array([0.3, 0.3, 0.24]))
    return frame, plate, cfw @ truth, rend.index == 0, roi


def _roi(frame, roi, **kw):  # type: ignore[no-untyped-def]
    det = CadDetector([_plate()], roi, options=CadOptions(**kw))
    pmap = backproject_depth(frame.camera, np.asarray(frame.depth_m))
    return det, det._roi_mask(frame, pmap, roi).reshape(frame.depth_m.shape)


def test_roi_keeps_a_thin_plate_lying_on_the_floor(floor_scene) -> None:  # type: ignore[no-untyped-def]
    frame, _, _, on_plate, roi = floor_scene
    _, keep = _roi(frame, roi)
    assert keep[on_plate].mean() > 0.6  # the 3 mm plate is inside the per-pixel band (2.5 x 2 mm noise + 4 mm)
    assert keep[~on_plate].mean() < 0.01  # the floor stays out
    _, band_only = _roi(frame, roi, thin_above_m=0.0)
    assert band_only[on_plate].mean() < 0.1  # without the window mean the plate is lost


def test_depth_scores_rank_the_true_pose_first(floor_scene) -> None:  # type: ignore[no-untyped-def]
    frame, plate, truth, _, roi = floor_scene
    _, keep = _roi(frame, roi)
    model = ppf.ppf_model(prepare(plate))
    slid = truth.copy()
    slid[:3, 3] += [0.012, 0.0, 0.0]  # half over the floor
    lifted = truth.copy()
    lifted[:3, 3] -= 0.03 * truth[:3, 3] / np.linalg.norm(truth[:3, 3])  # 3 cm towards the camera: seen through
    sc = ppf.depth_scores(model, np.stack([truth, slid, lifted]), frame.depth_m, keep, K, 0.003, 0.0036)
    assert sc[0] > sc[1] > 0 > sc[2]
    counts = ppf.depth_counts(model.points, model.normals, lifted[None], frame.depth_m, keep, K, 0.003, 0.0036)
    assert counts[0, 2] > 0.5 * counts[0, 3]  # most of the lifted plate's visible points are seen through


def test_region_refine_slides_and_turns_a_plate_back(floor_scene) -> None:  # type: ignore[no-untyped-def]
    frame, plate, truth, _, roi = floor_scene
    det, keep = _roi(frame, roi)
    det._camera_k = K
    det._depth = np.ascontiguousarray(frame.depth_m)
    prep = prepare(plate)
    off = np.eye(4)
    off[:3, :3] = Rotation.from_euler("z", 9, degrees=True).as_matrix()
    off[:3, 3] = [0.004, -0.003, 0.0]
    start = truth @ off  # slid 5 mm and turned 9 degrees in the plate's plane: the same top face
    out, moved = det._refine_region(plate, prep, start, keep)
    assert moved
    assert np.linalg.norm(out[:3, 3] - truth[:3, 3]) < 0.002
    rel = truth[:3, :3].T @ out[:3, :3]
    ang = np.degrees(np.arctan2(rel[1, 0], rel[0, 0])) % 90.0
    assert min(ang, 90.0 - ang) < 3.0
    bracket = {p.name: p for p in default_part_library()}["bracket"]  # not flat, no axis: left as it is
    same, moved = det._refine_region(bracket, prepare(bracket), start, keep)
    assert not moved and np.array_equal(same, start)


def test_a_pose_sunk_into_the_support_plane_is_refused(floor_scene) -> None:  # type: ignore[no-untyped-def]
    frame, plate, truth, _, roi = floor_scene
    det, _ = _roi(frame, roi)
    prep = prepare(plate)
    assert not det._sinks(prep, truth)
    sunk = truth.copy()
    sunk[:3, 3] += 0.012 * truth[:3, 3] / np.linalg.norm(truth[:3, 3])  # 12 mm further from the camera: in the floor
    assert det._sinks(prep, sunk)


def test_nms_keeps_distinct_poses_and_drops_symmetric_copies() -> None:
    cyl = {p.name: p for p in default_part_library()}["cylinder"]
    prep = prepare(cyl)
    a = np.eye(4)
    a[:3, 3] = [0.0, 0.0, 0.5]
    turned = a.copy()
    turned[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # about the axis: the same pose
    far = a.copy()
    far[:3, 3] += [0.05, 0.0, 0.0]
    tilted = a.copy()
    tilted[:3, :3] = Rotation.from_euler("x", 40, degrees=True).as_matrix()
    poses = np.stack([a, turned, far, tilted])
    kept, sc = ppf.nms_poses(poses, np.array([3.0, 5.0, 1.0, 2.0]), prep.centroid, 0.01, np.deg2rad(10), 10, prep.sym)
    assert np.allclose(sc, [5.0, 2.0, 1.0])  # the best of the two copies, then the others by score
    kept, sc = ppf.nms_poses(poses, np.array([3.0, 5.0, -1.0, 2.0]), prep.centroid, 0.01, np.deg2rad(10), 1, prep.sym)
    assert len(kept) == 1 and sc[0] == 5.0


def test_vectorised_reference_frames_match_the_scalar_ones() -> None:
    rng = np.random.default_rng(2)
    n = rng.normal(size=(50, 3))
    n[:3] = [[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0]]  # the degenerate axes and a plain one
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = rng.normal(size=(50, 3))
    fast = ppf.frames_to_x(p, n)
    slow = np.stack([ppf._frame_to_x(a, b) for a, b in zip(p, n, strict=True)])
    assert np.allclose(fast, slow, atol=1e-12)
    assert np.allclose(np.einsum("nij,nj->ni", fast[:, :3, :3], n), [1.0, 0.0, 0.0], atol=1e-9)
