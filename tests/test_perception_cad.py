"""CAD detection in the whole region of interest (`--segmenter cad`): PPF voting, the detector, factory, pipeline."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from normpos_grasp.errors import InputError
from normpos_grasp.perception.cad_detector import CadDetector, CadOptions, RegionOfInterest
from normpos_grasp.perception.factory import choose_segmenter
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.templates import ppf
from normpos_grasp.templates.prepared import prepare


def _sym_add(template, est, gt) -> float:  # type: ignore[no-untyped-def]
    prep = prepare(template)
    sub = prep.samples[::4]
    pe = sub @ est[:3, :3].T + est[:3, 3]
    best = np.inf
    for s in template.symmetry.transforms(continuous_steps=72):
        g = gt @ s
        best = min(best, float(np.mean(np.linalg.norm(pe - (sub @ g[:3, :3].T + g[:3, 3]), axis=1))))
    return best


@pytest.mark.parametrize("name", ["box", "bracket", "cylinder"])
def test_ppf_voting_recovers_a_posed_view(name: str) -> None:
    t = {p.name: p for p in default_part_library()}[name]
    prep = prepare(t)
    model = ppf.ppf_model(prep)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    pose[:3, 3] = [0.02, -0.01, 0.6]
    pts = prep.samples @ pose[:3, :3].T + pose[:3, 3]
    nrm = prep.normals @ pose[:3, :3].T
    seen = np.einsum("ij,ij->i", nrm, -pts) > 0  # faces towards the camera at the origin
    keep = ppf.voxel_downsample(pts[seen], model.step)
    rng = np.random.default_rng(3)
    sp = pts[seen][keep] + rng.normal(0.0, 0.0005, (len(keep), 3))
    poses, votes = ppf.vote_poses(model, sp, nrm[seen][keep], ppf.scene_references(len(sp), 4))
    best, _ = ppf.cluster_poses(poses, votes, prep.centroid, 0.1 * prep.diameter, np.deg2rad(15), 3, prep.sym)
    assert len(best) >= 1
    # the best-voted cluster is the view's pose, up to the part's symmetry (before any ICP)
    assert _sym_add(t, best[0], pose) < 0.1 * prep.diameter


def test_cluster_poses_merges_symmetric_copies() -> None:
    t = {p.name: p for p in default_part_library()}["cylinder"]
    prep = prepare(t)
    base = np.eye(4)
    base[:3, 3] = [0.0, 0.0, 0.5]
    turned = base.copy()
    turned[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()  # about the cylinder axis
    poses, votes = np.stack([base, turned]), np.array([5.0, 4.0])
    merged, mv = ppf.cluster_poses(poses, votes, prep.centroid, 0.01, np.deg2rad(10), 5, prep.sym)
    apart, av = ppf.cluster_poses(poses, votes, prep.centroid, 0.01, np.deg2rad(10), 5, None)
    assert len(merged) == 1 and mv[0] == 9.0
    assert len(apart) == 2


def test_nms_per_place_cap_keeps_a_second_place() -> None:
    # five distinct turns at one place outscore the single pose at another: without a per-place cap the budget of
    # three goes to the first place only (a big surface many wrong poses fit hides a small part's right pose)
    centroid = np.zeros(3)
    poses = []
    for k in range(5):
        p = np.eye(4)
        p[:3, :3] = Rotation.from_euler("z", 40 * k, degrees=True).as_matrix()
        p[:3, 3] = [0.0, 0.0, 0.6]
        poses.append(p)
    other = np.eye(4)
    other[:3, 3] = [0.1, 0.0, 0.6]
    poses.append(other)
    scores = np.array([10.0, 9.0, 8.0, 7.0, 6.0, 5.0])
    plain, _ = ppf.nms_poses(np.stack(poses), scores, centroid, 0.005, np.deg2rad(15), 3)
    capped, cs = ppf.nms_poses(np.stack(poses), scores, centroid, 0.005, np.deg2rad(15), 3, None, 2, 0.03)
    assert not any(np.allclose(q, other) for q in plain)
    assert any(np.allclose(q, other) for q in capped)
    assert list(cs) == [10.0, 9.0, 5.0]  # two at the first place, then the second place


def test_compiled_explained_pixels_match_the_kd_tree_rule() -> None:
    """ppf.explained_pixels (the detector's compiled pull-in step) against the per-pixel cKDTree rule it replaced:
    a posed bracket's surface plus noise, floor and clutter pixels, scale 1 and 1.05."""
    t = {p.name: p for p in default_part_library()}["bracket"]
    prep = prepare(t)
    rng = np.random.default_rng(7)
    h, w = 60, 80
    pmap = np.zeros((h, w, 3))
    cfo = np.eye(4)
    cfo[:3, :3] = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    cfo[:3, 3] = [0.0, 0.0, 0.7]
    surf = prep.samples[rng.integers(0, len(prep.samples), h * w // 2)] @ cfo[:3, :3].T + cfo[:3, 3]
    pts = np.concatenate([surf, cfo[:3, 3] + rng.uniform(-0.08, 0.08, (h * w - len(surf), 3))])
    pts += rng.normal(0.0, 0.002, pts.shape)  # noise of the order of the tolerance: pixels on both sides of it
    pmap[:] = pts[rng.permutation(h * w)].reshape(h, w, 3)
    allowed = rng.random((h, w)) < 0.8
    ofc = np.linalg.inv(cfo)
    for scale in (1.0, 1.05):
        r, bound, tol, noise = 0.6 * prep.diameter, 0.05 * prep.diameter + 0.01, 0.003, 0.0036
        got = ppf.explained_pixels(pmap, allowed, (5, 55, 3, 77), ofc, scale, prep, r, bound, tol, noise)
        sub = np.zeros((h, w), dtype=bool)
        sub[5:55, 3:77] = allowed[5:55, 3:77]
        vv, uu = np.nonzero(sub)
        p = pmap[vv, uu]
        po = (p @ ofc[:3, :3].T + ofc[:3, 3]) / scale
        near = np.linalg.norm(po - prep.centroid, axis=1) < r
        d, _ = prep.tree.query(po[near], distance_upper_bound=bound)
        sel = np.flatnonzero(near)[d * scale < tol + 2.5 * noise * p[near, 2] ** 2]
        want = vv[sel] * w + uu[sel]
        assert 200 < len(want) < int(sub.sum())  # both explained and unexplained pixels in the box
        np.testing.assert_array_equal(got, want)


@pytest.fixture(scope="module")
def scene():  # type: ignore[no-untyped-def]
    from normpos_grasp.sim.cameras import CameraOptions
    from normpos_grasp.sim.dataset import generate_frame
    from normpos_grasp.sim.scene import SceneOptions

    lib = default_part_library()
    parts = [t for t in lib if t.name in ("box", "bracket", "cylinder", "plate")]
    so = SceneOptions(count=3, seed=21, clutter=0.0)
    sf = generate_frame(so, "d435", CameraOptions(distance_m=(0.55, 0.6), tilt_deg=(0, 10)), seed=4, library=parts)
    ix, iy = so.bin_inner_size_m
    f = so.bin_floor_thickness_m
    box = np.eye(4)
    box[2, 3] = f + 0.12
    roi = RegionOfInterest(np.array([0.0, 0.0, 1.0, -f]), box, np.array([ix, iy, 0.24]))
    return sf, parts, roi


def test_detector_finds_the_parts_without_masks(scene) -> None:  # type: ignore[no-untyped-def]
    sf, parts, roi = scene
    det = CadDetector(parts, roi).detect(sf.frame)
    assert len(det.instances) == len(det.fits) == len(det.normpositions) >= 2
    right = 0
    for fit, inst, n in zip(det.fits, det.instances, det.normpositions, strict=True):
        assert fit.accepted and fit.instance_id == inst.instance_id == n.instance_id
        assert inst.label == fit.template.label and inst.mask.any()
        errs = [
            _sym_add(t, fit.frame_from_object, sf.world_from_object[k])
            for k, t in enumerate(sf.layout.templates)
            if t.name == fit.template.name
        ]
        assert errs, f"{fit.template.name} accepted but not in the scene"
        assert min(errs) < 0.1 * prepare(fit.template).diameter  # every accepted pose is right
        right += 1
    visible = [k for k in range(len(sf.layout.templates)) if sf.visib_fractions[k] >= 0.5]
    assert right >= len(visible) - 1


def test_detection_is_deterministic_and_leaves_the_frame(scene) -> None:  # type: ignore[no-untyped-def]
    sf, parts, roi = scene
    depth = sf.frame.depth_m.copy()
    a = CadDetector(parts, roi).detect(sf.frame)
    b = CadDetector(parts, roi).detect(sf.frame)
    assert np.array_equal(depth, sf.frame.depth_m)
    assert [f.template.name for f in a.fits] == [f.template.name for f in b.fits]
    for fa, fb in zip(a.fits, b.fits, strict=True):
        assert np.allclose(fa.frame_from_object, fb.frame_from_object)


def test_pipeline_takes_the_detected_poses(scene) -> None:  # type: ignore[no-untyped-def]
    from normpos_grasp.pipeline import perceive

    sf, parts, roi = scene
    res = perceive(sf.frame, CadDetector(roi=roi), parts)
    assert res.fits and all(f.accepted for f in res.fits)
    assert [f.instance_id for f in res.fits] == [n.instance_id for n in res.normpositions]
    assert res.timings_ms["fit"] == 0.0  # not fitted again


def test_cad_needs_a_library_and_valid_options(scene) -> None:  # type: ignore[no-untyped-def]
    sf, _, roi = scene
    with pytest.raises(InputError, match="template library"):
        CadDetector(roi=roi).segment(sf.frame)
    with pytest.raises(InputError):
        CadOptions(min_new_share=0.0)


def test_factory_registers_cad_and_auto_keeps_the_depth_fallback() -> None:
    lib = default_part_library()
    choice = choose_segmenter("cad", library=lib)
    assert choice.kind == "cad" and isinstance(choice.segmenter, CadDetector)
    assert choice.segmenter.library is not None and len(choice.segmenter.library) == len(lib)
    pytest.importorskip("onnxruntime")
    # a label the bundled model does not know: the depth segmenter, never cad by default (its precision is short)
    assert choose_segmenter("auto", labels={"nut_m12"}, library=lib).kind == "depth"
    assert choose_segmenter("auto", labels={"nut_m12"}).kind == "depth"


def _hex_nut():  # type: ignore[no-untyped-def]
    import trimesh

    from normpos_grasp.records.template import Symmetry, Template

    mesh = trimesh.creation.cylinder(radius=0.0139, height=0.011, sections=6)  # 24 mm across flats
    rots = []
    for k in range(1, 6):
        r = np.eye(4)
        r[:3, :3] = Rotation.from_euler("z", 60 * k, degrees=True).as_matrix()
        rots.append(r)
    return Template(name="hexnut", label="hexnut", mesh=mesh, symmetry=Symmetry(discrete=tuple(rots)))


def test_symmetry_axis_of_discrete_groups() -> None:
    from normpos_grasp.templates.edges import symmetry_axis

    axis, period = symmetry_axis(_hex_nut())  # type: ignore[misc]
    assert np.allclose(np.abs(axis), [0, 0, 1]) and np.isclose(np.degrees(period), 60.0)
    cyl = {p.name: p for p in default_part_library()}["cylinder"]  # continuous axis plus a half turn only
    assert symmetry_axis(cyl) is None


def test_refine_turn_finds_the_nut_flats_on_the_outline() -> None:
    from normpos_grasp.camera.model import Camera
    from normpos_grasp.camera.render import render
    from normpos_grasp.templates.edges import refine_turn

    nut = _hex_nut()
    prep = prepare(nut)
    cam = Camera(np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]]), 640, 480)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("xyz", [180 + 8, 5, 17], degrees=True).as_matrix()  # seen from above
    truth[:3, 3] = [0.01, -0.005, 0.55]
    depth = render(cam, [(nut.mesh, truth)]).depth_m
    floor = depth == 0
    depth[floor] = 0.58  # a support surface behind it
    turned = truth.copy()
    off = np.eye(4)
    off[:3, :3] = Rotation.from_euler("z", 14, degrees=True).as_matrix()
    turned = truth @ off  # 14 degrees off about the nut's axis: the same top face, other corners
    out, turn = refine_turn(nut, prep, turned, cam.K, depth, 0.003)
    rel = np.linalg.inv(truth[:3, :3]) @ out[:3, :3]
    ang = np.degrees(np.arctan2(rel[1, 0], rel[0, 0])) % 60.0
    assert turn != 0.0
    assert min(ang, 60.0 - ang) < 2.0  # back on the flats (modulo the 60-degree symmetry)
    same, none = refine_turn(nut, prep, truth, cam.K, depth, 0.003)
    assert none == 0.0 or abs(np.degrees(none)) < 2.0


@pytest.mark.parametrize("command", [["measure", "scene", "--out", "o"], ["estimate", "split", "--out", "r.csv"]])
def test_every_segmenting_command_accepts_cad(command: list[str]) -> None:
    from normpos_grasp.cli.main import build_parser

    args = build_parser().parse_args([*command, "--segmenter", "cad"])
    assert args.segmenter == "cad"
