"""Verification: a wrong template is rejected by the depth evidence over its silhouette; one pose per object."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from normpos_grasp.camera.model import Camera
from normpos_grasp.geometry.transforms import invert_pose, look_at, make_pose
from normpos_grasp.records.normpos import NormPosition
from normpos_grasp.records.template import Template
from normpos_grasp.sim.parts import part_library_by_name
from normpos_grasp.templates import kernels
from normpos_grasp.templates.fit import FitContext, FitOptions, fit_template
from normpos_grasp.templates.select import model_overlap, one_pose_per_object
from normpos_grasp.templates.synthetic import SyntheticView, make_normpos, render_views

CAM = Camera(np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]]), 640, 480)
CAMERA_FROM_WORLD = invert_pose(look_at(np.array([0.25, -0.35, 0.55]), np.zeros(3), up=np.array([0, 0, 1.0])))
TABLE = trimesh.creation.box(extents=(1.0, 1.0, 0.02))


def _on_table(parts: list[tuple[Template, np.ndarray]], seed: int) -> SyntheticView:
    """Parts (template, xy offset in metres) resting on a table (z = 0), seen obliquely from 0.7 m (camera frame)."""
    objects = []
    for t, xy in parts:
        zmin = float(np.asarray(t.mesh.vertices)[:, 2].min())
        objects.append((t, CAMERA_FROM_WORLD @ make_pose(np.eye(3), np.array([xy[0], xy[1], -zmin]))))
    table = CAMERA_FROM_WORLD @ make_pose(np.eye(3), np.array([0.0, 0.0, -0.01]))
    return render_views(CAM, objects, np.random.default_rng(seed), extra_meshes=[(TABLE, table)])


@pytest.fixture(scope="module")
def lib() -> dict[str, Template]:
    return part_library_by_name()


def test_silhouette_evidence_counts() -> None:
    """Explained: depth within tol in the window; front: the pixel reads between tol and front_lim in front."""
    depth = np.full((20, 20), 1.0)
    tol = 0.004
    pv = np.array([[0.0, 0.0, 1.001], [0.0, 0.0, 1.01], [0.0, 0.0, 1.05], [0.0, 0.0, 0.95]])
    uv = np.array([[10, 10], [10, 10], [10, 10], [10, 10]], dtype=np.int64)
    n_in, n_exp, n_front = kernels.silhouette_evidence(pv, uv, depth, tol, 2, 3 * tol)
    # 1.001: explained; 1.01: 10 mm behind the measured surface (front band); 1.05: behind by more (an occluder);
    # 0.95: in front of the measured surface (see-through, the free-space test's business)
    assert (n_in, n_exp, n_front) == (4, 1, 1)
    off = np.array([[-1, 3], [25, 3]], dtype=np.int64)
    assert kernels.silhouette_evidence(pv[:2], off, depth, tol, 2, 3 * tol) == (0, 0, 0)


def test_wrong_template_rejected_by_silhouette_evidence(lib: dict[str, Template]) -> None:
    """A box (60x40x30) seen with the bracket template forced: the bracket's legs fit the box's faces, but the
    model runs right behind the table and the box's unexplained surface; the right template passes."""
    view = _on_table([(lib["box"], np.zeros(2))], seed=1)
    n = view.normpos[0]
    ctx = FitContext(CAM, view.depth_m)
    right = fit_template(n, lib["box"], FitOptions(), ctx)
    assert right.accepted, right.reason
    assert right.extra["front_share"] <= 0.01 and right.extra["explained_share"] > 0.9
    wrong = fit_template(n, lib["bracket"], FitOptions(), ctx)
    assert not wrong.accepted
    assert "unexplained surface" in wrong.reason
    assert wrong.extra["front_share"] > right.extra["front_share"]


def _half(n: NormPosition, left: bool) -> NormPosition:
    """The left or right half (by image column) of a norm-position: a fragment as a segmenter may cut it."""
    u = n.pixels[:, 0]
    cut = float(np.median(u))
    keep = u <= cut if left else u > cut
    mask = np.zeros_like(n.mask)
    mask[n.pixels[keep, 1], n.pixels[keep, 0]] = True
    return make_normpos(n.points[keep], n.normals[keep], n.pixels[keep], mask, n.label, 1 if left else 2)


def test_overlapping_fits_on_one_object_collapse_to_one(lib: dict[str, Template]) -> None:
    view = _on_table([(lib["cylinder"], np.zeros(2)), (lib["box"], np.array([0.12, 0.05]))], seed=2)
    ctx = FitContext(CAM, view.depth_m)
    cyl = view.normpos[0]
    frags = [_half(cyl, True), _half(cyl, False)]
    box = view.normpos[1]
    box = make_normpos(box.points, box.normals, box.pixels, box.mask, box.label, 3)
    fits = [fit_template(f, lib["cylinder"], FitOptions(), ctx) for f in frags]
    fits.append(fit_template(box, lib["box"], FitOptions(), ctx))
    assert all(f.accepted for f in fits), [f.reason for f in fits]
    assert model_overlap(fits[0], fits[1]) > 0.8 and model_overlap(fits[0], fits[2]) == 0.0
    out = one_pose_per_object(fits, [*frags, box])
    assert [f.instance_id for f in out] == [1, 2, 3]
    kept = [f for f in out[:2] if f.accepted]
    dropped = [f for f in out[:2] if not f.accepted]
    assert len(kept) == 1 and len(dropped) == 1
    assert dropped[0].extra["duplicate_of"] == kept[0].instance_id and "same object" in dropped[0].reason
    assert out[2].accepted  # another object is not a duplicate
    assert one_pose_per_object(out) == out  # idempotent: nothing left to suppress
