"""The install-time warm-up fits its ray-cast box correctly on every path it compiles."""

from __future__ import annotations

import trimesh  # noqa: F401  (a hard dependency: imported, never skipped)

from normpos_grasp.templates.warmup import warm_up


def test_warm_up_fits_are_accepted_and_pick_the_right_template() -> None:
    seconds, fits = warm_up()
    assert seconds > 0.0
    assert [f.accepted for f in fits] == [True, True, True], [f.reason for f in fits]
    assert [f.template.name for f in fits] == ["warmup_box"] * 3
