"""The compiled sphere proofs (collision.spheres) give the verdicts of the numpy passes they replaced in
`CollisionWorld.configs_clear`, bit for bit: on random scenes and on spheres tuned to touch a box or another sphere
to the last bit (where another order of the same sums would flip the verdict)."""

from __future__ import annotations

import numpy as np

from normpos_grasp.collision.spheres import spheres_apart, spheres_near_boxes, spheres_off_boxes
from normpos_grasp.typing import BoolArray, FloatArray


def _off_boxes_numpy(
    centres: FloatArray, radii: FloatArray, lo: FloatArray, hi: FloatArray, held_rows: BoolArray, held_index: int
) -> BoolArray:
    """The numpy pass configs_clear ran before (the reference)."""
    clear = np.ones(len(centres), dtype=bool)
    box_lo = (centres - radii[..., None]).min(axis=1) - 1e-9
    box_hi = (centres + radii[..., None]).max(axis=1) + 1e-9
    pairs = np.all(lo[None] <= box_hi[:, None], axis=2) & np.all(hi[None] >= box_lo[:, None], axis=2)
    if held_index >= 0:
        pairs[held_rows, held_index] = False
    kk, ee = np.nonzero(pairs)
    if len(kk):
        c = centres[kk]
        gap = np.minimum(np.maximum(c, lo[ee][:, None]), hi[ee][:, None]) - c
        d2 = np.einsum("pmi,pmi->pm", gap, gap)
        clear[kk[np.any(d2 <= radii[kk] * radii[kk], axis=1)]] = False
    return clear


def _near_numpy(centres: FloatArray, radii: FloatArray, lo: FloatArray, hi: FloatArray) -> BoolArray:
    """The numpy pass CollisionWorld.near ran before (the reference)."""
    c = centres[:, None, :]
    gap = np.minimum(np.maximum(c, lo[None]), hi[None]) - c
    d2 = np.einsum("kni,kni->kn", gap, gap)
    return np.any(d2 <= (radii * radii)[:, None], axis=1)


def _apart_numpy(
    arm_c: FloatArray, r: FloatArray, mask: BoolArray, low: np.ndarray, extra_c: FloatArray, extra_r: FloatArray
) -> BoolArray:
    """The numpy passes configs_clear ran before (the reference)."""
    d = np.linalg.norm(arm_c[:, :, None] - arm_c[:, None], axis=-1) - (r[:, None] + r[None])
    clear = ~np.any((d <= 0) & mask[None], axis=(1, 2))
    d = np.linalg.norm(arm_c[:, low][:, :, None] - extra_c[:, None], axis=-1) - (
        r[low][None, :, None] + extra_r[:, None]
    )
    return clear & ~np.any(d <= 0, axis=(1, 2))


def _touching_radius(d2: float, inside: bool) -> float:
    """The largest radius whose square is below d2 (inside False) or the smallest whose square is not (True)."""
    r = float(np.sqrt(d2))
    while r * r >= d2:
        r = float(np.nextafter(r, 0.0))
    while inside and r * r < d2:
        r = float(np.nextafter(r, np.inf))
    return r


def test_spheres_off_boxes_match_the_numpy_pass() -> None:
    rng = np.random.default_rng(11)
    lo = rng.uniform(-0.5, 0.3, size=(12, 3))
    hi = lo + rng.uniform(0.01, 0.3, size=(12, 3))
    for trial in range(30):
        k, m = int(rng.integers(1, 40)), int(rng.integers(1, 12))
        centres = rng.uniform(-0.7, 0.7, size=(k, m, 3))
        radii = rng.uniform(0.0, 0.15, size=(k, m))
        held_rows = rng.random(k) < 0.5
        held_index = int(rng.integers(-1, len(lo)))
        got = spheres_off_boxes(centres, radii, lo, hi, held_rows, held_index)
        assert np.array_equal(got, _off_boxes_numpy(centres, radii, lo, hi, held_rows, held_index)), trial


def test_spheres_touching_a_box_to_the_last_bit_get_the_numpy_verdict() -> None:
    rng = np.random.default_rng(12)
    lo, hi = np.array([[0.0, 0.0, 0.0]]), np.array([[0.1, 0.2, 0.05]])
    verdicts = set()
    for _ in range(400):
        c = rng.uniform(-0.2, 0.4, size=(1, 1, 3))
        gap = np.minimum(np.maximum(c, lo[:, None]), hi[:, None]) - c
        d2 = float(np.einsum("pmi,pmi->pm", gap, gap)[0, 0])
        if d2 == 0.0:
            continue
        for inside in (False, True):
            radii = np.array([[_touching_radius(d2, inside)]])
            want = _off_boxes_numpy(c, radii, lo, hi, np.zeros(1, dtype=bool), -1)
            got = spheres_off_boxes(c, radii, lo, hi, np.zeros(1, dtype=bool), -1)
            assert np.array_equal(got, want)
            verdicts.add(bool(want[0]))
    assert verdicts == {True, False}  # both sides of the boundary were tested


def test_arm_spheres_apart_match_the_numpy_pass_at_random_and_at_contact() -> None:
    rng = np.random.default_rng(13)
    s, t = 8, 5
    r = rng.uniform(0.03, 0.08, size=s)
    mask = np.triu(rng.random((s, s)) < 0.6, 1)
    low = np.array([0, 1, 2])
    for trial in range(30):
        k = int(rng.integers(1, 30))
        arm_c = rng.uniform(-0.4, 0.4, size=(k, s, 3))
        extra_c = rng.uniform(-0.4, 0.4, size=(k, t, 3))
        extra_r = rng.uniform(0.0, 0.1, size=(k, t))
        got = spheres_apart(arm_c, r, mask, low, extra_c, extra_r)
        assert np.array_equal(got, _apart_numpy(arm_c, r, mask, low, extra_c, extra_r)), trial
    # a tool sphere at exactly (to the bit) the distance where it touches a low link's sphere, from either side
    verdicts = set()
    none = np.zeros((s, s), dtype=bool)
    for _ in range(300):
        arm_c = rng.uniform(-0.4, 0.4, size=(1, s, 3))
        extra_c = rng.uniform(-0.4, 0.4, size=(1, 1, 3))
        arm_c[0, 1:] += 10.0  # only link 0 near the tool sphere
        dist = float(np.linalg.norm(arm_c[0, 0] - extra_c[0, 0]))
        for step in (-1, 0, 1):
            er = dist - r[0]
            for _ in range(abs(step)):
                er = float(np.nextafter(er, np.inf if step > 0 else -np.inf))
            extra_r = np.array([[er]])
            far = np.full(s, 1e-3)
            far[0] = r[0]
            want = _apart_numpy(arm_c, far, none, np.array([0]), extra_c, extra_r)
            got = spheres_apart(arm_c, far, none, np.array([0]), extra_c, extra_r)
            assert np.array_equal(got, want)
            verdicts.add(bool(want[0]))
    assert verdicts == {True, False}


def test_spheres_near_boxes_match_the_numpy_pass_at_random_and_at_contact() -> None:
    rng = np.random.default_rng(14)
    lo = rng.uniform(-0.5, 0.3, size=(16, 3))
    hi = lo + rng.uniform(0.01, 0.3, size=(16, 3))
    for trial in range(30):
        k = int(rng.integers(1, 12))
        centres = rng.uniform(-0.7, 0.7, size=(k, 3))
        radii = rng.uniform(0.0, 0.15, size=k)
        assert np.array_equal(spheres_near_boxes(centres, radii, lo, hi), _near_numpy(centres, radii, lo, hi)), trial
    one_lo, one_hi = lo[:1], hi[:1]
    verdicts = set()
    for _ in range(400):
        c = rng.uniform(-0.7, 0.7, size=(1, 3))
        gap = np.minimum(np.maximum(c[:, None], one_lo[None]), one_hi[None]) - c[:, None]
        d2 = float(np.einsum("kni,kni->kn", gap, gap)[0, 0])
        if d2 == 0.0:
            continue
        for inside in (False, True):
            radii = np.array([_touching_radius(d2, inside)])
            want = _near_numpy(c, radii, one_lo, one_hi)
            assert np.array_equal(spheres_near_boxes(c, radii, one_lo, one_hi), want)
            verdicts.add(bool(want[0]))
    assert verdicts == {True, False}
