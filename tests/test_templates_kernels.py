"""Compiled fitting kernels agree with plain numpy / scipy references; fit_many equals fit_best in a loop."""

from __future__ import annotations

from pathlib import Path

import numba  # noqa: F401  (a hard dependency: imported, never skipped)
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from normpos_grasp.camera.model import Camera
from normpos_grasp.geometry.transforms import make_pose, random_rotation
from normpos_grasp.records.template import Template
from normpos_grasp.templates import kernels
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_best, fit_many
from normpos_grasp.templates.icp import candidates
from normpos_grasp.templates.library import load_library
from normpos_grasp.templates.prepared import PreparedTemplate, normal_bins, prepare
from normpos_grasp.templates.synthetic import render_views

REPO = Path(__file__).resolve().parents[1]
CAM = Camera(np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]]), 640, 480)


@pytest.fixture(scope="module")
def lib() -> dict[str, Template]:
    return {t.name: t for t in load_library(REPO / "examples" / "templates")}


def _queries(prep: PreparedTemplate, seed: int, n: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """Points near and far from the surface with noisy normals (some disagreeing with the nearest sample's)."""
    rng = np.random.default_rng(seed)
    i = rng.choice(len(prep.samples), n)
    spread = rng.choice([0.001, 0.01, 0.3 * prep.diameter], size=(n, 1))
    y = prep.samples[i] + rng.normal(0.0, 1.0, (n, 3)) * spread
    ny = prep.normals[i] + rng.normal(0.0, 0.6, (n, 3))
    return y, ny / np.linalg.norm(ny, axis=1, keepdims=True)


@pytest.mark.parametrize("name", ["l_bracket", "cube_40mm"])
def test_exact_correspondences_match_kd_tree_reference(lib: dict[str, Template], name: str) -> None:
    prep = prepare(lib[name])
    y, ny = _queries(prep, 3)
    r, d, sel = kernels.correspond_many(y, ny, True, prep.samples, prep.normals, prep.grid, prep.kd)
    # reference: scipy KD-tree nearest; where its normal disagrees, the nearest sample of the normal's bin
    dist, idx = prep.tree.query(y)
    ok = np.einsum("pd,pd->p", prep.normals[idx], ny) > kernels.NORMAL_COS
    bad = np.flatnonzero(~ok)
    d2, i2 = prep.nearest_binned(y[bad], normal_bins(ny[bad]))
    dist[bad], idx[bad] = d2, i2
    ok[bad] = np.einsum("pd,pd->p", prep.normals[i2], ny[bad]) > kernels.NORMAL_COS
    ref_d = np.where(ok, dist, np.inf)
    assert len(bad) > 20  # the normal-bin fallback is exercised
    np.testing.assert_array_equal(np.isfinite(d), np.isfinite(ref_d))
    fin = np.isfinite(d)
    np.testing.assert_allclose(d[fin], ref_d[fin], rtol=0, atol=1e-12)
    ref_r = np.einsum("pd,pd->p", y - prep.samples[sel], prep.normals[sel])
    np.testing.assert_allclose(r, ref_r, atol=1e-12)


@pytest.mark.parametrize("name", ["l_bracket", "cube_40mm"])
def test_sorted_candidate_scan_finds_the_same_nearest_samples(lib: dict[str, Template], name: str) -> None:
    # the fit's exact correspondences (cells' candidates sorted by distance to the centre, scan cut short)
    prep = prepare(lib[name])
    y, ny = _queries(prep, 5)
    r_ref, d_ref, _ = kernels.correspond_many(y, ny, True, prep.samples, prep.normals, prep.grid, prep.kd)
    pose = np.eye(4)[None]
    args = (pose, np.ones(1), y, ny, True, np.inf, prep.samples, prep.normals, prep.grid, prep.kd, candidates(prep))
    r, d = kernels.correspond_posed(*args)
    np.testing.assert_array_equal(d[0], d_ref)
    np.testing.assert_array_equal(r[0], r_ref)


def test_grid_correspondences_follow_the_distance_grid(lib: dict[str, Template]) -> None:
    prep = prepare(lib["l_bracket"])
    y, ny = _queries(prep, 4)
    r, d, sel = kernels.correspond_many(y, ny, False, prep.samples, prep.normals, prep.grid, prep.kd)
    idx, inside = prep.grid_lookup(y)
    ok = np.einsum("pd,pd->p", prep.normals[idx], ny) > kernels.NORMAL_COS
    bad = np.flatnonzero(~ok)
    s2, in2 = prep.grid_lookup_binned(y[bad], normal_bins(ny[bad]))
    idx[bad] = np.where(s2 >= 0, s2, len(prep.samples) - 1)
    inside[bad] = in2
    ok[bad] = np.einsum("pd,pd->p", prep.normals[idx[bad]], ny[bad]) > kernels.NORMAL_COS
    ref_d = np.where((inside > 0) & ok, np.linalg.norm(y - prep.samples[idx], axis=1), np.inf)
    np.testing.assert_array_equal(sel, idx)
    np.testing.assert_allclose(d, ref_d, atol=1e-12)
    np.testing.assert_allclose(r, np.einsum("pd,pd->p", y - prep.samples[idx], prep.normals[idx]), atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 7))
def test_solve_matches_numpy(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    m = rng.normal(size=(n, n))
    a = m @ m.T + 1e-3 * np.eye(n)
    b = rng.normal(size=n)
    x = kernels._solve(a.copy(), b.copy(), n)
    np.testing.assert_allclose(a @ x, b, atol=1e-8 * max(1.0, float(np.abs(b).max())))


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000))
def test_nearest_rows_match_sorted_distances(seed: int) -> None:
    rng = np.random.default_rng(seed)
    data = rng.random((int(rng.integers(3, 60)), 33))
    query = rng.random((int(rng.integers(1, 20)), 33))
    out = kernels.nearest_rows(query, np.ascontiguousarray(data.T), 3)
    d2 = ((query[:, None] - data[None]) ** 2).sum(-1)
    ref = np.argsort(d2, axis=1, kind="stable")[:, :3]
    np.testing.assert_allclose(np.take_along_axis(d2, out, 1), np.take_along_axis(d2, ref, 1), rtol=1e-12)


def test_icp_recovers_a_perturbed_pose(lib: dict[str, Template]) -> None:
    from normpos_grasp.templates.icp import icp

    t = lib["l_bracket"]
    prep = prepare(t)
    rng = np.random.default_rng(5)
    gt = make_pose(random_rotation(rng), [0.01, -0.02, 0.6])
    view = render_views(CAM, [(t, gt)], rng)
    pts = np.asarray(view.normpos[0].points)[:: max(1, len(view.normpos[0].points) // 200)]
    nrm = np.asarray(view.normpos[0].normals)[:: max(1, len(view.normpos[0].points) // 200)]
    turn = Rotation.from_rotvec(np.deg2rad(6) * np.array([0.6, -0.8, 0.0])).as_matrix()
    start = make_pose(turn, [0.003, -0.002, 0.003]) @ np.linalg.inv(gt)
    thr = np.full(len(pts), 0.003)
    poses, scales, frac = icp(
        prep,
        start[None],
        np.ones(1),
        pts,
        nrm,
        thr,
        iterations=15,
        exact=False,
        fit_scale=False,
        scale_tolerance=0.05,
        max_corr_start=0.15 * prep.diameter,
    )
    err = poses[0] @ gt
    assert np.linalg.norm(err[:3, 3]) < 0.002
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 1.0
    assert frac[0] > 0.8 and scales[0] == 1.0


def test_fit_many_equals_fit_best_in_a_loop(lib: dict[str, Template]) -> None:
    rng = np.random.default_rng(11)
    scene = [
        (lib["l_bracket"], make_pose(random_rotation(rng), [-0.06, 0.0, 0.6])),
        (lib["cube_40mm"], make_pose(random_rotation(rng), [0.06, 0.02, 0.65])),
    ]
    view = render_views(CAM, scene, rng)
    ctx = FitContext(CAM, view.depth_m)
    templates = list(lib.values())
    loop = [fit_best(n, templates, FitOptions(), ctx) for n in view.normpos]
    many = fit_many(view.normpos, templates, FitOptions(), ctx, workers=2)
    assert len(many) == len(loop) == 2
    for a, b in zip(many, loop, strict=True):
        assert (a.template.name, a.accepted) == (b.template.name, b.accepted)
        assert a.accepted
        np.testing.assert_allclose(a.frame_from_object, b.frame_from_object, atol=1e-12)
        assert a.score == b.score


@pytest.mark.parametrize("fit_scale", [False, True])
def test_point_term_sums_match_closed_form(fit_scale: bool) -> None:
    from normpos_grasp.templates.icp import point_to_point_normal_equations

    rng = np.random.default_rng(2)
    y = rng.normal(0, 0.05, (50, 3))
    e = rng.normal(0, 0.002, (50, 3))
    w = rng.uniform(0, 1, 50)
    c = np.array([0.01, -0.02, 0.03])
    ye = np.cross(y, e)
    outer = np.einsum("p,pi,pj->ij", w, y, y)
    pp = np.concatenate(
        [
            [w.sum()],
            w @ y,
            [outer[0, 0], outer[0, 1], outer[0, 2], outer[1, 1], outer[1, 2], outer[2, 2]],
            w @ e,
            w @ ye,
            [w @ np.einsum("pi,pi->p", y, e)],
        ]
    )
    dof = 7 if fit_scale else 6
    a = np.zeros((7, 7))
    b = np.zeros(7)
    kernels._add_point_terms(a, b, pp, c, fit_scale)
    a = np.triu(a) + np.triu(a, 1).T
    a_ref, b_ref = point_to_point_normal_equations(y[None], e[None], w[None], c, fit_scale=fit_scale)
    np.testing.assert_allclose(a[:dof, :dof], a_ref[0], atol=1e-14)
    np.testing.assert_allclose(-b[:dof], -b_ref[0], atol=1e-14)


def test_compiled_fpfh_matches_numpy_reference(lib: dict[str, Template]) -> None:
    from normpos_grasp.templates.features import fpfh, fpfh_reference, voxel_downsample

    prep = prepare(lib["l_bracket"])
    keep = voxel_downsample(prep.samples, prep.voxel)
    pts, nrm = prep.samples[keep], prep.normals[keep]
    np.testing.assert_allclose(fpfh(pts, nrm, prep.voxel * 2.5), fpfh_reference(pts, nrm, prep.voxel * 2.5), atol=1e-12)


def test_knn_points_match_kd_tree() -> None:
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(8)
    pts = rng.random((300, 3))
    idx = kernels.knn_points(pts, 16)
    ref_d, _ = cKDTree(pts).query(pts, k=16)
    d = np.linalg.norm(pts[idx] - pts[:, None], axis=-1)
    np.testing.assert_allclose(d, ref_d, atol=1e-12)
    assert np.all(idx[:, 0] == np.arange(300))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=60), st.integers(0, 10_000))
def test_kth_smallest_matches_sort(values: list[float], seed: int) -> None:
    arr = np.array(values)
    k = seed % len(arr)
    assert kernels._kth_smallest(arr.copy(), len(arr), k) == np.sort(arr)[k]


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_voxel_downsample_matches_numpy_reference(seed: int) -> None:
    from normpos_grasp.templates.features import voxel_downsample, voxel_downsample_reference

    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 400))
    pts = rng.normal(0.0, 0.05, (n, 3))
    if seed % 3 == 0 and n > 1:  # repeated points: equal distances to the voxel centre, the lower index wins
        pts[n // 2 :] = pts[: n - n // 2]
    voxel = float(rng.choice([0.001, 0.004, 0.02, 1.0]))
    out = voxel_downsample(pts, voxel)
    np.testing.assert_array_equal(out, voxel_downsample_reference(pts, voxel))


def test_radius_neighbours_match_kd_tree_query() -> None:
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(4)
    pts = rng.random((250, 3)) * 0.1
    idx, dist, valid = kernels.radius_neighbours(pts, 13, 0.012)
    ref_d, ref_i = cKDTree(pts).query(pts, k=13, distance_upper_bound=0.012)
    ref_valid = np.isfinite(ref_d[:, 1:])
    assert 0 < ref_valid.sum() < ref_valid.size  # some neighbourhoods cut by the radius
    np.testing.assert_array_equal(valid, ref_valid)
    np.testing.assert_array_equal(idx, np.where(ref_valid, ref_i[:, 1:], 0))
    np.testing.assert_allclose(dist, np.where(ref_valid, ref_d[:, 1:], 1.0), rtol=0, atol=1e-15)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_mean_closest_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 0.03, (int(rng.integers(1, 200)), 3))
    b = rng.normal(0.0, 0.03, (int(rng.integers(1, 200)), 3))
    if seed % 2:  # ties along the sort axis
        a[:, 0] = np.round(a[:, 0], 2)
        b[:, 0] = np.round(b[:, 0], 2)
    ref = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1).min(1)).mean()
    assert kernels.mean_closest(a, b) == pytest.approx(ref, rel=1e-12, abs=1e-15)


def test_depth_scores_equal_the_separate_depth_tests(lib: dict[str, Template]) -> None:
    """The fused score (its window scan stops at the first supporting depth) counts as visible_points,
    project_pinhole, depth_evidence and silhouette_evidence do, on rendered frames and on poses off the data."""
    prep = prepare(lib["l_bracket"])
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(4):
        pose = make_pose(random_rotation(rng), [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 0.6])
        view = render_views(CAM, [(lib["l_bracket"], pose)], rng)
        depth = np.ascontiguousarray(view.depth_m, dtype=np.float64)
        for shift in (0.0, 0.004, 0.02):
            cfo = pose.copy()
            cfo[:3, 3] += rng.normal(0.0, shift, 3)
            tol = 0.004
            cam = (CAM.fx, CAM.fy, CAM.cx, CAM.cy)
            got = kernels.depth_scores(prep.samples, prep.normals, cfo, 1.0, prep.spacing, *cam, depth, tol, 2, 3 * tol)
            pv, nv = kernels.visible_points(prep.samples, prep.normals, cfo, 1.0, prep.spacing)
            uv = kernels.project_pinhole(pv, CAM.fx, CAM.fy, CAM.cx, CAM.cy)
            ev = kernels.depth_evidence(pv, nv, uv, depth, tol, 2)
            _, n_exp, n_front = kernels.silhouette_evidence(pv, uv, depth, tol, 2, 3 * tol)
            assert got == (len(pv), *ev, n_exp, n_front)
            checked += int(ev[0] > 0)
    assert checked >= 4  # the supported (early-stopping) branch was exercised
