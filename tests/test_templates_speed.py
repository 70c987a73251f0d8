"""Fitting shortcuts keep results: score bounds are upper bounds, closed-form ICP equations, template floor."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from normpos_grasp.camera.model import Camera
from normpos_grasp.geometry.transforms import make_pose, random_rotation
from normpos_grasp.records.template import Template
from normpos_grasp.templates import fit as fit_module
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_best
from normpos_grasp.templates.icp import point_to_point_normal_equations
from normpos_grasp.templates.library import load_library
from normpos_grasp.templates.prepared import prepare
from normpos_grasp.templates.scoring import consistency_neighbours, evaluate, score_bounds
from normpos_grasp.templates.synthetic import render_views

REPO = Path(__file__).resolve().parents[1]
CAM = Camera(np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]]), 640, 480)


@pytest.fixture(scope="module")
def lib() -> dict[str, Template]:
    return {t.name: t for t in load_library(REPO / "examples" / "templates")}


def _view(t: Template, seed: int):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    gt = make_pose(random_rotation(rng), [rng.uniform(-0.05, 0.05), 0.0, rng.uniform(0.5, 0.8)])
    return gt, render_views(CAM, [(t, gt)], rng)


def test_score_bound_is_an_upper_bound_and_reuses_correspondences(lib: dict[str, Template]) -> None:
    t = lib["l_bracket"]
    prep = prepare(t)
    gt, view = _view(t, 4)
    meas = fit_module._prepare_measurement(view.normpos[0], FitOptions())
    rng = np.random.default_rng(0)
    poses = []
    for k in range(6):  # the right pose and perturbed / wrong ones
        turn = make_pose(random_rotation(rng) if k > 2 else np.eye(3), rng.normal(0, 0.003 * k, 3))
        poses.append(turn @ np.linalg.inv(gt))
    poses_a = np.array(poses)
    scales = np.ones(len(poses_a))
    nb = consistency_neighbours(meas.pts_score)
    bound, r, d = score_bounds(prep, poses_a, scales, meas.pts_score, meas.nrm_score, meas.thr_score, nb)
    for i, pose in enumerate(poses_a):
        args = (prep, pose, 1.0, meas.pts_score, meas.nrm_score, meas.thr_score, meas.tree, meas.viewpoint)
        kw = {"camera": CAM, "depth_m": view.depth_m, "camera_from_frame": np.eye(4)}
        full = evaluate(*args, **kw)
        reused = evaluate(*args, **kw, neighbours=nb, corr=(r[i], d[i]))
        for field in ("score", "inlier_ratio", "rmse_m", "coverage", "free_space_violation", "consistency"):
            assert getattr(reused, field) == pytest.approx(getattr(full, field), rel=1e-9, abs=1e-12)
        assert bound[i] >= full.score - 1e-12
    assert bound[0] > 0.5  # the right pose is not trivially bounded away


def test_closed_form_point_term_matches_stacked_jacobians(lib: dict[str, Template]) -> None:
    t = lib["cube_40mm"]
    prep = prepare(t)
    rng = np.random.default_rng(1)
    y = prep.samples[rng.choice(len(prep.samples), 80, replace=False)] + rng.normal(0, 1e-3, (80, 3))
    w = rng.uniform(0, 1, (2, 80))
    ys = np.stack([y, y * 1.01])
    e = rng.normal(0, 1e-3, ys.shape)
    c = prep.centroid
    # stacked per-point Jacobians [-[y]x, I, -(y - c)] of the point-to-point residual
    jp = np.zeros((2, 80, 3, 7))
    for h in range(2):
        for p in range(80):
            yy = ys[h, p]
            jp[h, p, :, :3] = -np.array([[0, -yy[2], yy[1]], [yy[2], 0, -yy[0]], [-yy[1], yy[0], 0]])
            jp[h, p, :, 3:6] = np.eye(3)
            jp[h, p, :, 6] = -(yy - c)
    a_ref = np.einsum("hpki,hp,hpkj->hij", jp, w, jp)
    b_ref = -np.einsum("hpki,hp,hpk->hi", jp, w, e)
    a, b = point_to_point_normal_equations(ys, e, w, c, fit_scale=True)
    np.testing.assert_allclose(a, a_ref, atol=1e-12)
    np.testing.assert_allclose(b, b_ref, atol=1e-12)


def test_template_floor_keeps_fit_best_decisions(lib: dict[str, Template], monkeypatch: pytest.MonkeyPatch) -> None:
    templates = list(lib.values())
    results = []
    for seed, name in ((2, "l_bracket"), (3, "cube_40mm")):
        _, view = _view(lib[name], seed)
        npos = replace(view.normpos[0], label="")
        ctx = FitContext(CAM, view.depth_m)
        results.append((npos, ctx, fit_best(npos, templates, FitOptions(), ctx)))
    original = fit_module._fit_prepared
    monkeypatch.setattr(fit_module, "_fit_prepared", lambda n, t, m, o, c, floor, t0: original(n, t, m, o, c, 0.0, t0))
    for npos, ctx, fast in results:
        full = fit_best(npos, templates, FitOptions(), ctx)
        assert (fast.template.name, fast.accepted) == (full.template.name, full.accepted)
        assert fast.score == pytest.approx(full.score)
        np.testing.assert_allclose(fast.frame_from_object, full.frame_from_object, atol=1e-9)
