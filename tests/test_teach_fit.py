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
