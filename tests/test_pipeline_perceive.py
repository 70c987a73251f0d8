"""pipeline.perceive on one synthetic bin frame with ground-truth instances: accepted fits lie near the truth."""

from __future__ import annotations

import mujoco  # noqa: F401  (physics settling of the bin scene; a hard dependency)
import numpy as np
import pytest
import trimesh  # noqa: F401  (a hard dependency: imported, never skipped)
from scipy.spatial import cKDTree

from normpos_grasp.camera.model import RGBDFrame
from normpos_grasp.cell import resolve_cell
from normpos_grasp.pipeline import perceive
from normpos_grasp.records.instance import Instance
from normpos_grasp.records.template import Template
from normpos_grasp.sim.cell_scene import cell_camera, compose_cell_scene
from normpos_grasp.sim.dataset import SyntheticFrame, render_frame
from normpos_grasp.sim.parts import default_part_library
from normpos_grasp.sim.render import make_renderer
from normpos_grasp.sim.sensor import sensor_preset

SEED = 9017  # not used by other tests


class _MustNotSegment:
    def segment(self, frame: RGBDFrame) -> list[Instance]:
        raise AssertionError("perceive() must use the given instances, not call the segmenter")


class _Fixed:
    def __init__(self, instances: list[Instance]) -> None:
        self.instances = instances
        self.calls = 0

    def segment(self, frame: RGBDFrame) -> list[Instance]:
        self.calls += 1
        return list(self.instances)


@pytest.fixture(scope="module")
def scene() -> tuple[SyntheticFrame, list[Template]]:
    cell = resolve_cell("ur5e_bin_parallel")
    library = default_part_library()
    layout = compose_cell_scene(cell, 3, SEED, library)
    camera = cell_camera(cell, "d435", (640, 480))
    renderer = make_renderer(layout, camera.width, camera.height, "raycast")  # no OpenGL needed, deterministic
    try:
        sf = render_frame(layout, renderer, camera, sensor_preset("d435"), np.random.default_rng(SEED))
    finally:
        renderer.close()
    return sf, library


def _centre_error_and_add(template: Template, est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """(centre distance m, ADD(-S) m) of pose `est` vs `gt` (4, 4), world frame.

    BOP's convention: ADD over the discrete symmetries for parts without a continuous symmetry, ADD-S (mean
    closest-point distance) for parts with one, whose rotation about that axis is not observable (a sphere's at all).
    """
    verts = np.asarray(template.mesh.vertices, dtype=np.float64)
    centre = verts.mean(axis=0)
    pe = verts @ est[:3, :3].T + est[:3, 3]
    pg = verts @ gt[:3, :3].T + gt[:3, 3]
    d = float(np.linalg.norm((est[:3, :3] @ centre + est[:3, 3]) - (gt[:3, :3] @ centre + gt[:3, 3])))
    if template.symmetry.continuous:
        closest, _ = cKDTree(pg).query(pe)
        return d, float(np.mean(closest))
    adds = []
    for s in template.symmetry.transforms():
        g = gt @ s
        adds.append(float(np.mean(np.linalg.norm(pe - (verts @ g[:3, :3].T + g[:3, 3]), axis=1))))
    return d, min(adds)


def test_perceive_with_true_instances_fits_near_truth(scene: tuple[SyntheticFrame, list[Template]]) -> None:
    sf, library = scene
    instances = [i for i in sf.instances if sf.visib_fractions[i.source_id] >= 0.5]
    assert instances, "the scene must show at least one part well"
    result = perceive(sf.frame, _MustNotSegment(), library, instances=instances)

    assert set(result.timings_ms) == {"segment", "measure", "fit"}
    assert result.plan is None
    assert len(result.normpositions) == len(result.fits) == len(instances)
    by_id = {i.instance_id: i for i in instances}
    accepted = 0
    for npos, fit in zip(result.normpositions, result.fits, strict=True):
        inst = by_id[npos.instance_id]
        truth = sf.layout.templates[inst.source_id]
        assert npos.frame == "world"
        # the measured surface lies on the true part: its centroid within a part's size of the true centre
        true_centre = sf.world_from_object[inst.source_id][:3, 3]
        assert np.linalg.norm(npos.centroid - true_centre) < truth.diameter_m
        if not fit.accepted:
            assert fit.reason
            continue
        accepted += 1
        assert fit.template.name == truth.name
        centre_err, add = _centre_error_and_add(truth, fit.world_from_object, sf.world_from_object[inst.source_id])
        assert centre_err < 0.005, f"{truth.name}: centre off by {centre_err * 1e3:.1f} mm"
        assert add < 0.005, f"{truth.name}: ADD(-S) {add * 1e3:.1f} mm"
    assert accepted >= 1, [f.reason for f in result.fits]
    assert {f.instance_id for f in result.accepted_fits} <= set(by_id)


def test_perceive_calls_the_segmenter_without_instances(scene: tuple[SyntheticFrame, list[Template]]) -> None:
    sf, library = scene
    empty = _Fixed([])
    result = perceive(sf.frame, empty, library)
    assert empty.calls == 1
    assert result.instances == [] and result.normpositions == [] and result.fits == []
    assert result.accepted_fits == []
    assert set(result.timings_ms) == {"segment", "measure", "fit"}
