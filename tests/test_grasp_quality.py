"""Grip mechanics (`grasp.quality`): antipodal contacts, friction cones, pad area, weight and torque; the cup's seal
on the fitted surface and its load; the verdicts checked against MuJoCo where the outcome is not obvious."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from normpos_grasp.cell import load_cell
from normpos_grasp.cell.config import CellConfig
from normpos_grasp.geometry import make_pose, rotation_from_rotvec
from normpos_grasp.grasp.quality import (
    CALIBRATION,
    QualityOptions,
    judge,
    pad_footprint,
    parallel_mechanics,
    predicted_success,
    suction_mechanics,
)
from normpos_grasp.grasp.synthesis import tcp_frame
from normpos_grasp.records.template import Template
from normpos_grasp.sim.parts import default_part_library

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "cells"
DOWN = np.array([0.0, 0.0, -1.0])


@pytest.fixture(scope="module")
def cell() -> CellConfig:
    return load_cell(EXAMPLES / "ur5e_bin_parallel.yaml")


@pytest.fixture(scope="module")
def parts() -> dict[str, Template]:
    return {t.name: t for t in default_part_library()}


def _pinch(centre: np.ndarray, closing: np.ndarray, depth: float = 0.0) -> np.ndarray:
    """A straight-down pinch with the TCP `depth` below `centre`, jaws closing along `closing`."""
    return tcp_frame(DOWN, closing, np.asarray(centre, dtype=np.float64) - DOWN * depth)


def test_flat_bar_across_its_faces_holds(cell: CellConfig, parts: dict[str, Template]) -> None:
    bar = parts["bar"]  # 100 x 25 x 25 mm along x
    pose = make_pose(None, [0.5, 0.0, 0.0225])
    mech = judge("parallel", bar.mesh, bar.mass_kg, pose, _pinch(pose[:3, 3], np.array([0.0, 1.0, 0.0])), cell.tool)
    assert mech.ok and mech.reason == ""
    assert mech.area_m2 > 3e-4  # a 25 x 25 mm face (less what the band trims) under each 27 mm pad
    assert mech.cone_angle_rad < 1e-6 and 0.0 < mech.load_ratio < 0.1
    assert mech.success == predicted_success(mech.margin) > 0.9


def test_rolled_bar_between_flat_pads_turns(cell: CellConfig, parts: dict[str, Template]) -> None:
    bar = parts["bar"]
    for roll_deg, ok in ((5.0, True), (25.0, False), (45.0, False)):
        pose = make_pose(rotation_from_rotvec([np.deg2rad(roll_deg), 0.0, 0.0]), [0.5, 0.0, 0.03])
        mech = judge("parallel", bar.mesh, bar.mass_kg, pose, _pinch(pose[:3, 3], np.array([0.0, 1.0, 0.0])), cell.tool)
        assert mech.ok is ok, (roll_deg, mech)
        if not ok:
            assert mech.reason == "friction_cone" and mech.success == 0.0


def test_sphere_point_contacts_are_antipodal(cell: CellConfig, parts: dict[str, Template]) -> None:
    sphere = parts["sphere"]
    pose = make_pose(None, [0.5, 0.0, 0.0325])
    centred = judge(
        "parallel", sphere.mesh, sphere.mass_kg, pose, _pinch(pose[:3, 3], np.array([1.0, 0, 0])), cell.tool
    )
    assert centred.ok, centred
    # TCP 2 cm above the centre: the fingertips reach 7 mm below the TCP... pads on the upper cap only, the squeeze
    # line through points above the equator stays horizontal (symmetric contacts), the part is still held
    high = judge(
        "parallel",
        sphere.mesh,
        sphere.mass_kg,
        pose,
        _pinch(pose[:3, 3] + [0, 0, 0.02], np.array([1.0, 0, 0])),
        cell.tool,
    )
    assert high.ok and high.area_m2 < centred.area_m2


def test_gravity_torque_about_the_grasp_axis(cell: CellConfig, parts: dict[str, Template]) -> None:
    bar = parts["bar"]
    pose = make_pose(None, [0.5, 0.0, 0.0225])
    weak = QualityOptions(grip_force_n=3.0)
    footprint = pad_footprint(cell.tool)
    closing = np.array([0.0, 1.0, 0.0])
    centre = parallel_mechanics(bar.mesh, bar.mass_kg, pose, _pinch(pose[:3, 3], closing), footprint, weak)
    off = parallel_mechanics(bar.mesh, bar.mass_kg, pose, _pinch(pose[:3, 3] + [0.04, 0, 0], closing), footprint, weak)
    assert centre.ok and not off.ok and off.reason == "slip_torque"
    assert off.load_ratio > 1.0 > centre.load_ratio
    # at the full grip force the same offset grasp holds, with a smaller margin than at the centre
    strong_off = parallel_mechanics(bar.mesh, bar.mass_kg, pose, _pinch(pose[:3, 3] + [0.04, 0, 0], closing), footprint)
    strong_centre = parallel_mechanics(bar.mesh, bar.mass_kg, pose, _pinch(pose[:3, 3], closing), footprint)
    assert strong_off.ok and strong_off.load_ratio > strong_centre.load_ratio


def test_nothing_between_the_pads(cell: CellConfig, parts: dict[str, Template]) -> None:
    cube = parts["cube"]
    pose = make_pose(None, [0.5, 0.0, 0.03])
    beside = _pinch(pose[:3, 3] + [0.0, 0.2, 0.0], np.array([1.0, 0, 0]))
    mech = judge("parallel", cube.mesh, cube.mass_kg, pose, beside, cell.tool)
    assert not mech.ok and mech.reason == "pad_contact"


def test_suction_seal_on_the_fitted_surface(parts: dict[str, Template]) -> None:
    ring, plate = parts["ring"], parts["plate"]  # ring OD 60, ID 36: a 12 mm annulus
    ring_pose = make_pose(None, [0.5, 0.0, 0.0175])
    on_annulus = tcp_frame(DOWN, np.array([1.0, 0, 0]), ring_pose[:3, 3] + [0.024, 0.0, 0.0075])
    mech = suction_mechanics(ring.mesh, ring.mass_kg, ring_pose, on_annulus)
    assert not mech.ok and mech.reason == "seal"
    # on an exact fit (no margin for its error) a 10 mm cup seals on the annulus, but 24 mm off the centre of mass
    # the ring's weight peels it off
    exact = QualityOptions(cup_diameter_m=0.01, seal_margin_m=0.0)
    small = suction_mechanics(ring.mesh, ring.mass_kg, ring_pose, on_annulus, exact)
    assert not small.ok and small.reason == "suction_torque", small
    plate_pose = make_pose(None, [0.5, 0.0, 0.014])
    on_face = tcp_frame(DOWN, np.array([1.0, 0, 0]), plate_pose[:3, 3] + [0.0, 0.0, 0.004])
    assert suction_mechanics(plate.mesh, plate.mass_kg, plate_pose, on_face).ok


def test_suction_seal_leaves_room_for_the_fit_error() -> None:
    import trimesh

    from normpos_grasp.records.tool import suction_tool

    # a 60 x 30 mm top face: a 30 mm cup seals only on an exact fit, so it is refused; a 24 mm cup keeps 3 mm a side
    block = Template("block", "block", trimesh.creation.box((0.06, 0.03, 0.04)), shape="box", mass_kg=0.2)
    pose = make_pose(None, [0.5, 0.0, 0.02])
    centre = tcp_frame(DOWN, np.array([1.0, 0, 0]), pose[:3, 3] + [0.0, 0.0, 0.02])
    exact = QualityOptions(cup_diameter_m=0.03, seal_margin_m=0.0)
    assert suction_mechanics(block.mesh, block.mass_kg, pose, centre, exact).ok
    mech = suction_mechanics(block.mesh, block.mass_kg, pose, centre, QualityOptions(cup_diameter_m=0.03))
    assert not mech.ok and mech.reason == "seal"
    assert suction_mechanics(block.mesh, block.mass_kg, pose, centre, QualityOptions(cup_diameter_m=0.024)).ok
    # judge takes the tool's own cup: 24 mm seals there, 40 mm does not (whatever the options' default cup)
    small, large = suction_tool("cup24", 0.15, cup_diameter_m=0.024), suction_tool("cup40", 0.15, cup_diameter_m=0.04)
    assert judge("suction", block.mesh, block.mass_kg, pose, centre, small).ok
    assert judge("suction", block.mesh, block.mass_kg, pose, centre, large).reason == "seal"


def test_suction_payload_torque(parts: dict[str, Template]) -> None:
    import trimesh

    # a steel block 80 x 60 x 30 mm (1.1 kg): held at its centre, peeled off when the cup sits 25 mm off it
    block = Template("block", "block", trimesh.creation.box((0.08, 0.06, 0.03)), shape="box", mass_kg=1.13)
    pose = make_pose(None, [0.5, 0.0, 0.025])
    centre = tcp_frame(DOWN, np.array([1.0, 0, 0]), pose[:3, 3] + [0.0, 0.0, 0.015])
    assert suction_mechanics(block.mesh, block.mass_kg, pose, centre).ok
    off = centre.copy()
    off[0, 3] += 0.025  # the cup's lip reaches the block's edge: judged on an exact fit, no margin for its error
    mech = suction_mechanics(block.mesh, block.mass_kg, pose, off, QualityOptions(seal_margin_m=0.0))
    assert not mech.ok and mech.reason == "suction_torque"
    heavy = replace(block, mass_kg=4.0)
    assert suction_mechanics(heavy.mesh, heavy.mass_kg, pose, centre).reason == "suction_load"


def test_predicted_success_table() -> None:
    margins = np.linspace(-0.5, 1.0, 31)
    p = [predicted_success(float(m)) for m in margins]
    assert all(a <= b for a, b in zip(p, p[1:], strict=False))
    assert predicted_success(0.0) == 0.0 and predicted_success(float("nan")) == 0.0
    assert predicted_success(1.0) == CALIBRATION[-1][1]


def test_mechanics_agree_with_mujoco_on_the_leaning_bar(cell: CellConfig, parts: dict[str, Template]) -> None:
    """A bar leaning on an 8 mm plate, pinched straight down at its centre: pitched 22 degrees (its side faces
    vertical) it holds; rolled 22 degrees about its long axis the pads close on two edges and MuJoCo turns it in
    the jaws (a slip) after the lift starts. The mechanics say the same before any physics runs."""
    pytest.importorskip("mujoco")
    import trimesh

    from normpos_grasp.loop import _physics_gripper
    from normpos_grasp.sim.physics import validate_grasp

    bar = parts["bar"]
    floor = 0.01  # the example cell's bin floor
    statics = [(b.name, b.world_from_box, b.size) for b in cell.static_boxes]
    tilt = np.deg2rad(22.0)
    c, s = np.cos(tilt), np.sin(tilt)
    block = Template("block", "block", trimesh.creation.box((0.12, 0.04, 0.008)), shape="plate", mass_kg=0.05)
    cases = []
    # rolled: lying along x, one edge on the floor, its rising underside on the block's edge
    rolled = make_pose(rotation_from_rotvec([tilt, 0.0, 0.0]), [0.5, -0.02, floor + 0.0125 * (c + s)])
    edge = 0.009 / np.tan(tilt) - 0.0125 * (c - s)
    cases.append((rolled, make_pose(None, [0.5, -0.02 + edge + 0.02, floor + 0.004]), False))
    # pitched: about y, its low end on the floor, resting on the block's edge
    cz = floor + 0.05 * s + 0.0125 * c
    pitched = make_pose(rotation_from_rotvec([0.0, -tilt, 0.0]), [0.48, 0.0, cz])
    cases.append((pitched, make_pose(None, [0.48 + 0.035, 0.0, floor + 0.004]), True))
    for pose, block_pose, holds in cases:
        grasp = _pinch(pose[:3, 3] + [0.0, 0.0, 0.004], np.array([0.0, 1.0, 0.0]))  # tips 9 mm below the centre
        mech = judge("parallel", bar.mesh, bar.mass_kg, pose, grasp, cell.tool)
        outcome = validate_grasp(bar, pose, [(block, block_pose)], statics, _physics_gripper(cell), grasp, 0.06).outcome
        assert mech.ok is holds and (outcome == "held") is holds, (holds, mech, outcome)


def test_suction_on_an_unexplained_object_seals_only_on_its_measured_surface() -> None:
    from normpos_grasp.grasp.quality import measured_seal

    # measured points 1.5 mm apart (a D435 at about 0.9 m): a 60 x 40 mm flat top, and a 40 mm cylinder on its side
    xs, ys = np.meshgrid(np.arange(-0.03, 0.03, 0.0015), np.arange(-0.02, 0.02, 0.0015))
    flat = np.stack([xs.ravel() + 0.5, ys.ravel(), np.full(xs.size, 0.04)], axis=1)
    down_at = lambda x, z: tcp_frame(DOWN, np.array([1.0, 0, 0]), np.array([x, 0.0, z]))  # noqa: E731
    opts = QualityOptions(cup_diameter_m=0.03)
    assert measured_seal(flat, down_at(0.5, 0.04), opts)
    assert not measured_seal(flat, down_at(0.52, 0.04), opts)  # the lip hangs 3 mm over the measured edge
    assert not measured_seal(flat[::40], down_at(0.5, 0.04), opts)  # too few measured points under the cup
    r = 0.02
    ang = np.clip(ys.ravel() / r, -1.0, 1.0)
    side = np.stack([xs.ravel() + 0.5, ys.ravel(), r * np.sqrt(1.0 - ang**2)], axis=1)
    assert not measured_seal(side, down_at(0.5, r), opts)  # 17 mm off its crest the side has dropped 9.5 mm
    small = QualityOptions(cup_diameter_m=0.014, seal_margin_m=0.001)
    assert measured_seal(side, down_at(0.5, r), small)  # a 16 mm footprint on the crest drops 1.7 mm
