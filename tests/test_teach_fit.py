"""Taught parts in the fit: template preparation of parts made with trimesh (not shipped, not in bench_teach)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from normpos_grasp.geometry.transforms import make_pose, random_rotation
from normpos_grasp.teach import check_cad
from normpos_grasp.templates.prepared import prepare, surface_axes

sys.path.insert(0, str(Path(__file__).parent))
import teach_parts


def _aligned(axes: np.ndarray, expected: np.ndarray) -> float:
    """Largest angle (degrees) between each column of `axes` and the same column of `expected`, sign-free."""
    cos = np.abs(np.sum(axes * expected, axis=0))
    return float(np.degrees(np.arccos(np.clip(cos.min(), -1.0, 1.0))))


@pytest.mark.parametrize("name", ["hex_nut", "thin_bracket", "asymmetric_block"])
def test_surface_axes_are_exact_and_turn_with_the_part(name: str) -> None:
    mesh = teach_parts.PARTS.get(name, teach_parts.asymmetric_block)()
    vals, axes = surface_axes(mesh)
    # the exact second moments, against a dense uniform sampling of the surface
    pts, _ = trimesh.sample.sample_surface(mesh, 200000, seed=1)
    cov = np.cov(pts.T, bias=True)
    assert np.allclose(np.sort(np.linalg.eigvalsh(cov))[::-1], vals, rtol=0.02)
    assert np.linalg.det(axes) == pytest.approx(1.0)
    rot = random_rotation(np.random.default_rng(4))
    turned = mesh.copy()
    turned.apply_transform(make_pose(rot, [5.0, -3.0, 2.0]))
    _, axes_t = surface_axes(turned)
    if np.min(np.diff(vals[::-1])) > 1e-6 * vals[0]:  # distinct moments: the axes are determined
        assert _aligned(axes_t, rot @ axes) < 1e-4


def test_a_mirror_symmetric_taught_part_keeps_its_axes_on_its_symmetry_planes(tmp_path: Path) -> None:
    """A T-profile (mirror planes x = 0 and y = 0) whose two cross-section moments are close: moments of random
    surface samples turned its axes by about 12 degrees off its faces (and its PCA hypotheses and flip variants
    with them); the thin bracket (an L extruded along x) keeps x exactly."""
    t = check_cad(teach_parts.write_part("t_profile", tmp_path))
    axes = prepare(t, persist=False).axes
    assert _aligned(np.abs(axes), np.abs(axes).round()) < 1e-6
    bracket = check_cad(teach_parts.write_part("thin_bracket", tmp_path))
    _, axes = surface_axes(bracket.mesh)
    assert np.max(np.abs(axes[0])) == pytest.approx(1.0, abs=1e-9)


def test_coarse_ranking_tells_a_small_part_from_its_upside_down_pose(tmp_path: Path) -> None:
    """A 28 mm top hat (made here) seen from 0.9 m: the inlier distance (2.5 sigma, 7 mm) is a quarter of the part, so
    the coarse inlier fraction barely tells the right pose from the part turned upside down (on its side it prefers
    the wrong one); the ranking that picks the poses to refine (`_coarse_rank`, the score bound) puts the right one
    first in (nearly) every view."""
    from dataclasses import replace

    from normpos_grasp.camera.model import Camera
    from normpos_grasp.geometry.transforms import invert_pose
    from normpos_grasp.templates import fit
    from normpos_grasp.templates.icp import icp
    from normpos_grasp.templates.symmetry import detect_symmetry
    from normpos_grasp.templates.synthetic import render_views

    profile = np.array([[0, -8], [14, -8], [14, -5], [8, -5], [8, 8], [0, 8]], dtype=np.float64)
    mesh = trimesh.creation.revolve(profile, sections=40)
    mesh.merge_vertices()
    mesh.export(str(tmp_path / "top_hat.stl"))
    t = check_cad(tmp_path / "top_hat.stl")
    t = replace(t, symmetry=detect_symmetry(t.mesh).symmetry)
    cam = Camera(np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]]), 640, 480)
    prep = prepare(t, persist=False)
    opts = fit.FitOptions()
    flip = make_pose(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0])[:3, :3], [0, 0, 0])
    by_rank = by_frac = 0
    for k, tilt_deg in enumerate((70, 90) * 3):  # tilted and on its side: where the fraction saturates
        rot = trimesh.transformations.rotation_matrix(np.deg2rad(180 + tilt_deg), [1, 0, 0])[:3, :3]
        gt = make_pose(rot, [0.02, 0.01, 0.9])
        view = render_views(cam, [(t, gt)], np.random.default_rng(k), noise_per_m2=0.0036)
        meas = fit._prepare_measurement(view.normpos[0], opts)
        starts = np.array([invert_pose(gt @ flip), invert_pose(gt)])  # object_from_frame: upside down, right
        poses, scales, frac = icp(
            prep, starts, np.ones(2), meas.pts_fit, meas.nrm_fit, meas.thr_fit, iterations=opts.coarse_iterations,
            exact=False, fit_scale=False, scale_tolerance=opts.scale_tolerance, max_corr_start=0.25 * prep.diameter,
        )  # fmt: skip
        rank = fit._coarse_rank(prep, poses, scales, frac, meas)
        by_rank += int(rank[1] > rank[0])
        by_frac += int(frac[1] > frac[0])
    assert by_rank >= 5 and by_rank > by_frac


class _Model:
    """A stand-in model: fixed masks with its own class names."""

    class_names = ("plate", "cube")

    def segment(self, frame: object) -> list:  # type: ignore[type-arg]
        from normpos_grasp.records.instance import Instance

        mask = np.zeros((4, 6), dtype=bool)
        mask[1:3, 1:4] = True
        return [Instance(mask, "plate", 0.9, 1, 0), Instance(~mask, "cube", 0.8, 2, 1)]


def test_a_model_that_lacks_library_labels_gives_class_agnostic_masks() -> None:
    from normpos_grasp.perception.factory import ClassAgnostic, choose_segmenter, for_library

    model = _Model()
    assert for_library(model, {"plate", "cube"}) is model  # knows every label: its classes are used
    agnostic = for_library(model, {"plate", "cube", "t_profile"})
    assert isinstance(agnostic, ClassAgnostic) and for_library(agnostic, {"t_profile"}) is agnostic
    found = agnostic.segment(object())  # type: ignore[arg-type]
    assert [i.label for i in found] == ["", ""] and [i.source_id for i in found] == [0, 1]
    assert agnostic.hints == {1: "plate", 2: "cube"}  # the model's class kept as a hint
    assert np.array_equal(found[0].mask, model.segment(None)[0].mask)
    # what competes for every mask beside the hinted class: the parts the model does not know
    from normpos_grasp.records.template import Template

    lib = [Template(n, n, trimesh.creation.box((0.02, 0.03, 0.04))) for n in ("plate", "cube", "t_profile", "nut")]
    assert [t.name for t in agnostic.unknown(lib)] == ["t_profile", "nut"]
    # the bundled model, for a library with a taught part: class-agnostic under 'model' ('auto' takes depth)
    choice = choose_segmenter("model", labels={"cube", "t_profile"})
    assert choice.kind == "model" and isinstance(choice.segmenter, ClassAgnostic)
    assert choose_segmenter("auto", labels={"cube", "t_profile"}).kind == "depth"
    assert not isinstance(choose_segmenter("model", labels={"cube"}).segmenter, ClassAgnostic)


def test_the_models_class_is_a_prior_that_a_taught_part_must_clearly_beat(monkeypatch: pytest.MonkeyPatch) -> None:
    """`pipeline._fit_hinted`: the hinted class's fit stands unless a taught template is accepted and explains the
    points clearly better (the hinted score below `class_ambiguity_ratio` of it); a rejected hinted fit yields."""
    from dataclasses import dataclass

    from normpos_grasp import pipeline
    from normpos_grasp.perception.factory import ClassAgnostic
    from normpos_grasp.records.template import Template, TemplateFit

    box = Template("box", "box", trimesh.creation.box((0.05, 0.03, 0.02)))
    tee = Template("t_profile", "t_profile", trimesh.creation.box((0.06, 0.03, 0.025)))
    scores: dict[str, tuple[float, bool]] = {}

    def fake_fit_many(nps, lib, *args, **kwargs):  # type: ignore[no-untyped-def]
        out = []
        for n in nps:
            t = box if n.label == "box" else tee
            assert n.label in ("box", "") and (n.label == "box" or [x.name for x in lib] == ["t_profile"])
            score, ok = scores[t.name]
            out.append(TemplateFit(t, np.eye(4), score, 0.001, 1.0, 1.0, 0.0, ok, instance_id=n.instance_id))
        return out

    monkeypatch.setattr(pipeline, "fit_many", fake_fit_many)

    class Model:
        class_names = ("box", "cube")

    seg = ClassAgnostic(Model())  # type: ignore[arg-type]
    seg.hints = {1: "box"}

    @dataclass(frozen=True)
    class N:
        label: str
        instance_id: int

    npos = N("", 1)
    opts = pipeline.PipelineOptions()

    def winner() -> str:
        (fit,) = pipeline._fit_hinted([npos], [box, tee], seg, opts, None)  # type: ignore[arg-type, list-item]
        return fit.template.name

    scores.update(box=(0.90, True), t_profile=(0.95, True))
    assert winner() == "box"  # about as good: the model's class stands (a T-profile top looks like a box top)
    scores.update(box=(0.60, True), t_profile=(0.95, True))
    assert winner() == "t_profile"  # clearly better
    scores.update(box=(0.95, False), t_profile=(0.70, True))
    assert winner() == "t_profile"  # the hinted fit was rejected (a T-profile the model called 'box')
    scores.update(box=(0.95, True), t_profile=(0.99, False))
    assert winner() == "box"
