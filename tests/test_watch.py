"""Zone watch (issue 22): the cell's `watch:` section, the detector on synthetic D435 frames (the arm, a held part
and noise never trigger it; a hand or a person in a zone does; outside the zones nothing does), the person rule,
the per-frame drift check, the driver's stop request, and the loop's resume rules (a zone stop, acknowledged,
then a fresh capture and plan, never the old plan)."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import numpy as np
import pytest

from normpos_grasp.camera.model import Camera, RGBDFrame
from normpos_grasp.camera.static_reference import StaticReference
from normpos_grasp.cell import resolve_cell
from normpos_grasp.cell.config import WatchSpec, ZoneSpec, cell_from_dict
from normpos_grasp.errors import CameraMoved, CellConfigError, DriverFault, ZoneIntrusion
from normpos_grasp.execution import DriverOptions, SafetyLimits, SimDriver
from normpos_grasp.geometry import invert_pose, make_pose, rotation_from_rotvec
from normpos_grasp.io.yaml_safe import load_yaml_file
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.sim.cameras import camera_intrinsics
from normpos_grasp.sim.sensor import sensor_preset
from normpos_grasp.watch.drift import DriftLimits, FrameDriftCheck
from normpos_grasp.watch.expected import ExpectedScene, joint_path, silhouette_depth
from normpos_grasp.watch.intrusion import IntrusionDetector
from normpos_grasp.watch.person import classify
from normpos_grasp.watch.synthetic import Intruder, SyntheticCellStream, cell_background, hand_box, person_shape

CELL = resolve_cell("ur5e_bin_parallel")
CELL_YAML = Path(__file__).resolve().parents[1] / "normpos_grasp" / "examples" / "cells" / "ur5e_bin_parallel.yaml"
HOME = np.asarray(CELL.home_q, dtype=np.float64)
SENSOR = sensor_preset("d435")
BIN = ZoneSpec("bin", np.array([0.28, -0.17, 0.0]), np.array([0.72, 0.17, 0.5]))
OPERATOR = ZoneSpec("operator_side", np.array([0.74, -0.45, 0.0]), np.array([0.95, 0.45, 0.6]))
SPEC = WatchSpec(zones=(BIN, OPERATOR), margin_m=0.02, downsample=1)
MOVE = np.array([0.5, 0.15, -0.2, 0.0, 0.0, 0.4])  # home -> a pose over the bin's far side
SIDEWAYS = (0.2, 0.09, 0.06)  # a hand-sized box lying along x, m


def _cell_dict() -> dict:
    return load_yaml_file(CELL_YAML)


def test_watch_section_is_validated() -> None:
    data = _cell_dict()
    data["watch"] = {
        "zones": [{"name": "bin", "min": [0.28, -0.17, 0.0], "max": [0.72, 0.17, 0.5]}],
        "arm_margin_m": 0.1,
        "stop": "protective",
        "require_ack": True,
        "approach_m": 0.2,
        "drift": {"max_translation_mm": 1.5},
    }
    cell = cell_from_dict(data, CELL_YAML.parent)
    assert cell.watch is not None and cell.watch.stop == "protective" and cell.watch.require_ack
    assert cell.watch.zones[0].name == "bin" and cell.watch.drift_max_translation_mm == 1.5
    assert cell.watch.approach_m == 0.2
    bad = [
        ({"zones": [], "arm_margin_m": 0.0}, "watch: nothing to watch"),
        ({"zones": [{"min": [0, 0, 0], "max": [1, 1, -1]}]}, r"watch.zones\[0\]: max"),
        ({"zones": [{"min": [0, 0, 0], "max": [1, 1, 1]}], "stop": "halt"}, "watch.stop"),
        ({"zones": [{"min": [0, 0, 0], "max": [1, 1, 1]}], "margn_m": 0.1}, "did you mean 'margin_m'"),
        ({"zones": [{"min": [0, 0, 0], "max": [1, 1, 1]}], "require_ack": "yes"}, "watch.require_ack"),
        ({"zones": [{"min": [0, 0, 0], "max": [1, 1, 1]}], "min_blob_px": 2.5}, "whole number"),
        ({"zones": [{"min": [0, 0, 0], "max": [1, 1, 1]}], "approach_m": -0.1}, "watch.approach_m"),
        ({"zones": [{"min": [0, 0, 0], "max": [1000, 1, 1]}]}, "millimetres"),
    ]
    for section, message in bad:
        data["watch"] = section
        with pytest.raises(CellConfigError, match=message):
            cell_from_dict(data, CELL_YAML.parent)


class _Scene:
    """The cell's camera at 320x240, a bin with parts, the arm moving from home towards the bin's far side; one per
    seed for the module (`_scene`), its reference frame (arm at home) rendered once."""

    def __init__(self, seed: int = 0) -> None:
        self.camera = camera_intrinsics("d435", (320, 240)).with_extrinsics(CELL.world_from_camera)
        self.arm = ArmModel.from_name("ur5e", CELL.world_from_base)
        background, _ = cell_background(CELL, self.camera, 6, seed)
        self.stream = SyntheticCellStream(self.camera, background, self.arm, CELL.tool, SENSOR, seed)
        self.reference = self.stream.frame(HOME)

    def detector(self, spec: WatchSpec = SPEC) -> IntrusionDetector:
        """A fresh detector (its expected scene learns from the frames it checks)."""
        expected = ExpectedScene(
            self.camera,
            self.reference,
            lambda z: np.asarray(SENSOR.depth_rms_m(z, self.camera.fx)),
            self.arm,
            CELL.tool,
            downsample=spec.downsample,
            k_sigma=spec.k_sigma,
            pad_m=spec.silhouette_pad_m,
            q_capture=HOME,
            static_boxes=CELL.static_boxes,
        )
        return IntrusionDetector.from_spec(expected, spec)

    @staticmethod
    def q(s: float) -> np.ndarray:
        return HOME + (0.5 - 0.5 * np.cos(np.pi * s)) * MOVE


@functools.cache
def _scene(seed: int) -> _Scene:
    return _Scene(seed)


def _path(s_now: float, ds: float = 0.05) -> np.ndarray:
    history = [(t, _Scene.q(t)) for t in np.arange(max(s_now - 0.2, 0.0), s_now + 1e-9, ds)]
    return joint_path(history, s_now - 0.1)


def test_arm_noise_and_held_part_never_trigger() -> None:
    scene = _scene(2)
    det = scene.detector()
    for s in np.linspace(0.0, 1.0, 13):
        # the frame shows the arm where it was a little earlier (latency) and a part hanging below the TCP
        shown_q = _Scene.q(max(s - 0.05, 0.0))
        tcp = scene.arm.fk(shown_q) @ CELL.tool.flange_from_tcp
        swing = tcp[:3, :3] @ np.array([np.sin(0.3 * np.sin(9 * s)), 0.0, 1.0])
        part = Intruder((), ((tcp[:3, 3], tcp[:3, 3] + 0.05 * swing, 0.025),))
        check = det.check(scene.stream.frame(shown_q, [part]), _path(s), held_radius_m=0.09)
        assert check.clear, [i.to_dict() for i in check.intrusions]


def test_hand_and_person_in_zones_are_caught_and_named() -> None:
    scene = _scene(2)
    det = scene.detector()
    check = det.check(scene.stream.frame(_Scene.q(0.6), [hand_box(np.array([0.42, -0.1, 0.12]))]), _path(0.6))
    assert not check.clear and check.intrusions[0].zone == "bin" and check.intrusions[0].label == "hand"
    assert abs(check.intrusions[0].centroid[0] - 0.42) < 0.06
    person = person_shape(np.array([0.82, 0.0, 0.35]), np.array([-1.0, 0.0, 0.0]))
    check = det.check(scene.stream.frame(_Scene.q(0.6), [person]), _path(0.6))
    assert not check.clear and check.intrusions[0].label == "person"
    assert {i.zone for i in check.intrusions} <= {"operator_side", "bin"}  # leaning over the strip, reaching in
    # a hand outside every zone and beyond the approach band (on the table, 16 cm from the bin's zone) is not an
    # intrusion
    outside = det.check(
        scene.stream.frame(_Scene.q(0.6), [hand_box(np.array([0.3, -0.4, 0.05]), SIDEWAYS)]), _path(0.6)
    )
    assert outside.clear and outside.n_candidates > 0  # seen as new, but in no watched volume
    # with a 25 cm band around the arm watched instead, a hand beside the moving tool is caught
    band = WatchSpec(zones=(), arm_margin_m=0.25, downsample=1)
    q = _Scene.q(0.6)
    tcp = (scene.arm.fk(q) @ CELL.tool.flange_from_tcp)[:3, 3]
    near_arm = hand_box(tcp + np.array([0.0, -0.2, 0.0]))
    check = scene.detector(band).check(scene.stream.frame(q, [near_arm]), _path(0.6))
    assert not check.clear and check.intrusions[0].zone == "arm_band"


def test_approach_band_catches_a_hand_coming_in_not_one_resting_or_noise_of_its_size() -> None:
    """A hand 6 cm outside the bin's zone (its leading part would be the first thing inside) stops the arm in the
    second frame that shows it nearer (two frames of evidence); appearing, resting or backing off in the band it
    does not, nor coming nearer beyond the band, nor with the band off; the same number of pixels of speckle in the
    band, or a blob one pixel short of `min_blob_px`, never does."""
    scene = _scene(2)
    q, path = _Scene.q(0.6), _path(0.6)
    det = scene.detector()
    hand = hand_box(np.array([0.3, -0.3, 0.05]), SIDEWAYS)  # its edge 6.5 cm from the zone (y >= -0.19)
    back, nearer = hand.moved(np.array([0.0, -0.03, 0.0])), hand.moved(np.array([0.0, 0.04, 0.0]))
    for shown in (hand, hand, back):  # appears, rests, backs off
        assert det.check(scene.stream.frame(q, [shown]), path).clear
    caught = det.check(scene.stream.frame(q, [nearer]), path)  # 7 cm nearer than the frame before
    assert not caught.clear and caught.intrusions[0].approaching and caught.intrusions[0].zone == "bin"
    assert 0.0 < caught.intrusions[0].distance_m < 0.05 and caught.intrusions[0].n_in_zone < det.min_blob_px
    off = IntrusionDetector(det.expected, det.zones, det.min_blob_px, approach_m=0.0)
    far = scene.detector()
    for shown in (back, nearer):
        assert off.check(scene.stream.frame(q, [shown]), path).clear
    for shown in (hand.moved(np.array([0.0, -0.14, 0.0])), hand.moved(np.array([0.0, -0.1, 0.0]))):
        assert far.check(scene.stream.frame(q, [shown]), path).clear  # 20 -> 16.5 cm away
    # speckle: as many pixels nearer than expected as the hand showed, scattered over the band beside the bin, in
    # two frames (other pixels each time)
    clear = scene.stream.frame(q)
    rng = np.random.default_rng(4)
    det = scene.detector()
    v, u = np.nonzero(clear > 0)
    pts = det.expected.world_points(v, u, clear[v, u])
    gap = det.zones.distance(pts).min(axis=1)
    keep = (gap > 0.01) & (gap < 0.12)
    for _ in range(2):
        pick = rng.choice(int(keep.sum()), min(int(keep.sum()), caught.intrusions[0].n_px), replace=False)
        speckle = clear.copy()
        speckle[v[keep][pick], u[keep][pick]] -= 0.1
        assert det.check(speckle, path).clear
    # a compact blob 10 cm above the table 6-8 cm beside the bin's zone, then 6 px (2 cm) nearer: one pixel short of
    # min_blob_px it never trips, at 16 px it does
    known = ~det.expected.unknown & (clear > 0)
    side = (pts[:, 1] < -0.25) & (pts[:, 1] > -0.27) & (gap > 0.05) & (pts[:, 0] < 0.45)
    r0, c0 = next(
        (int(a), int(b)) for a, b in zip(v[side], u[side], strict=True) if known[a : a + 4, b - 6 : b + 4].all()
    )
    for n, expect_clear in ((det.min_blob_px - 1, True), (16, False)):
        det = scene.detector()
        seen = []
        for c in (c0, c0 - 6):  # towards the zone: smaller columns on this side
            blob = clear.copy()
            block = np.zeros(clear.shape, dtype=bool)
            block[r0 : r0 + 4, c : c + 4] = True
            px = np.argwhere(block)[:n]
            blob[px[:, 0], px[:, 1]] -= 0.1
            seen.append(det.check(blob, path).clear)
        assert seen == [True, expect_clear], n


def test_arm_explains_its_own_pixels_in_3d_but_not_a_hand_that_overlaps_its_image() -> None:
    """A hand 12 cm from every link, seen inside the padded arm's image (mostly hidden under the arm), is still
    new: its back-projected points lie outside every padded capsule; the arm's own pixels are all explained."""
    scene = _scene(2)
    det = scene.detector()
    ex = det.expected
    q = _Scene.q(0.0)
    hand = hand_box(np.array([0.32, 0.14, 0.2]))
    assert ex.segments(q).distance(hand.sample_points(5)).min() > 0.12
    background = scene.stream.truth(None)
    truth = scene.stream.truth(q, [hand])
    arm_px = (scene.stream.truth(q) < np.where(background > 0, background, np.inf) - 1e-4) & (truth > 0)
    hand_px = truth < scene.stream.truth(q) - 1e-4
    near, far = silhouette_depth(ex.camera, ex.segments(_path(0.0), 0.0, ex.pad_m))
    assert (np.isfinite(near) & hand_px).sum() > 0.9 * hand_px.sum()  # inside the padded arm's image
    explained = ex.arm_explains(truth, _path(0.0), among=arm_px | hand_px)
    assert not (explained & hand_px).any() and (explained & arm_px).sum() >= 0.99 * (arm_px & ~hand_px).sum()
    check = det.check(scene.stream.frame(q, [hand]), _path(0.0))
    assert not check.clear and check.intrusions[0].zone == "bin"  # mostly hidden under the arm: a thin strip


def test_zone_depth_intervals_and_capsule_test_match_the_point_tests() -> None:
    scene = _scene(2)
    det = scene.detector()
    rng = np.random.default_rng(3)
    v, u = rng.integers(0, 240, 5000), rng.integers(0, 320, 5000)
    z = rng.uniform(0.2, 1.0, 5000)
    points = det.expected.world_points(v, u, z)
    by_pixel = np.full(len(v), -1)
    for i in range(len(det.zones.names)):
        by_pixel[(by_pixel < 0) & (z >= det.enter[i, v, u]) & (z <= det.leave[i, v, u])] = i
    assert (by_pixel == det.zones.zone_of(points)).all() and (by_pixel >= 0).sum() > 500
    segments = det.expected.segments(_path(0.5), 0.05, 0.06)
    margin = rng.uniform(0.0, 0.03, len(points))
    expect = (segments.distance(points) <= margin[:, None]).any(axis=1)
    assert (segments.within(points, margin) == expect).all() and expect.sum() > 50


def test_person_rule() -> None:
    rng = np.random.default_rng(0)
    torso = rng.uniform([-0.22, -0.12, 0.3], [0.22, 0.12, 0.6], (400, 3))
    hand = rng.uniform([-0.045, -0.1, 0.1], [0.045, 0.1, 0.13], (200, 3))
    speck = rng.uniform(-0.01, 0.01, (50, 3))
    assert [classify(torso), classify(hand), classify(speck)] == ["person", "hand", "object"]


def _board_frame(camera: Camera, bump: np.ndarray, texture: np.ndarray) -> RGBDFrame:
    """A textured plate at the table (z = 0, 0.6 x 0.45 m under the camera), seen through `camera` moved by `bump`
    (camera_from_camera_moved), with D435 RGB noise."""
    import cv2

    wfc = camera.require_world_from_camera() @ bump
    cfw = invert_pose(wfc)
    s = 0.6 / texture.shape[1]
    plane = np.column_stack([cfw[:3, 0], cfw[:3, 1], cfw[:3, :3] @ np.array([0.2, -0.225, 0.0]) + cfw[:3, 3]])
    h = camera.K @ plane @ np.array([[s, 0, 0.5 * s], [0, s, 0.5 * s], [0, 0, 1.0]])
    gray = cv2.warpPerspective(texture, h, (camera.width, camera.height), flags=cv2.INTER_LINEAR, borderValue=128)
    noisy = gray.astype(np.float64) + np.random.default_rng(int(1e6 * abs(bump).sum()) % 2**31).normal(
        0, 2.0, gray.shape
    )
    rgb = np.repeat(np.clip(noisy + 0.5, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
    return RGBDFrame(rgb, np.zeros((camera.height, camera.width)), camera)


def _drift_setup() -> tuple[Camera, FrameDriftCheck, np.ndarray]:
    import cv2

    from normpos_grasp.camera.calibration import ControlPoints

    rng = np.random.default_rng(5)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (450, 600)).astype(np.uint8), (0, 0), 2.0)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX)
    camera = camera_intrinsics("d435", (640, 480)).with_extrinsics(CELL.world_from_camera)
    world = np.array([[x, y, 0.0] for x in (0.28, 0.5, 0.72) for y in (-0.16, 0.0, 0.16)])
    pixels = camera.project(world @ camera.camera_from_world[:3, :3].T + camera.camera_from_world[:3, 3])
    names = tuple(f"p{i}" for i in range(len(world)))
    ref = StaticReference.from_calibration(
        camera, ControlPoints(names, world, pixels), _board_frame(camera, np.eye(4), texture).rgb
    )
    return camera, FrameDriftCheck(ref, camera, DriftLimits()), texture


def test_drift_check_catches_small_bumps_and_passes_a_still_camera() -> None:
    camera, check, texture = _drift_setup()
    for _ in range(3):
        report = check.check(_board_frame(camera, np.eye(4), texture))
        assert report.translation_mm < 1.0 and float(np.nanmax(report.pixel_shift_px)) < 0.35
    rng = np.random.default_rng(9)
    for k in range(6):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        bump = (
            make_pose(translation=0.002 * axis)
            if k % 2 == 0
            else make_pose(rotation_from_rotvec(np.radians(0.2) * axis))
        )
        with pytest.raises(CameraMoved, match=r"camera moved since calibration: .* mm, .* deg"):
            check.check(_board_frame(camera, bump, texture))


def test_stop_request_stops_a_simulated_move_and_latches() -> None:
    import threading

    driver = SimDriver(SafetyLimits.from_cell(CELL), q_home=HOME)
    driver.connect()
    try:
        timer = threading.Timer(0.3, lambda: driver.request_stop("test intrusion", False, {"zone": "bin"}))
        timer.start()
        with pytest.raises(ZoneIntrusion) as err:
            driver.move_joints([HOME + MOVE], 0.5, 1.0)
        assert err.value.detail["zone"] == "bin" and err.value.detail["stop_sent_at"] > 0
        assert float(np.max(np.abs(driver.state().q - (HOME + MOVE)))) > 0.05
        with pytest.raises(DriverFault, match="halted by ZoneIntrusion"):
            driver.gripper_close()
        driver.resume()
        driver.request_stop("protective", True)
        with pytest.raises(ZoneIntrusion):
            driver.move_joints([HOME], 0.5, 1.0)  # refused before anything is sent
    finally:
        driver.disconnect()
        driver.shutdown()


def test_loop_zone_stop_is_acknowledged_then_replanned_from_a_fresh_capture() -> None:
    from normpos_grasp.loop import SyntheticBinSource, run_cell_loop
    from normpos_grasp.sim.parts import default_part_library
    from normpos_grasp.watch.session import CellWatch
    from normpos_grasp.watch.synthetic import ThreadedStream

    source = SyntheticBinSource(CELL, count=2, seed=0, validate_physics=False)
    arm = ArmModel.from_name("ur5e", CELL.world_from_base)
    spec = WatchSpec(zones=(BIN,), margin_m=0.02, require_ack=True)
    opened: list[ThreadedStream] = []

    def open_stream(frame: RGBDFrame, driver: SimDriver) -> ThreadedStream:
        depth = source.last.rendering.depth_m
        scene = SyntheticCellStream(frame.camera, depth, arm, CELL.tool, SENSOR, len(opened), fast=True)
        # the first execution: a hand reaches into the bin 0.3 s in and withdraws 1 s after the stop; later: nothing
        hand = hand_box(np.array([0.42, -0.1, 0.12]))
        first = not opened

        def shown(t: float) -> list[Intruder]:
            gone = stopped and time.monotonic() > stopped[0] + 1.0
            return [hand] if first and t >= 0.3 and not gone else []

        stream = ThreadedStream(scene, lambda: driver.state().q, shown)
        opened.append(stream)
        return stream.start()

    asked: list[str] = []
    stopped: list[float] = []
    # the state watchdog is relaxed: the synthetic stream shares this process's two loaded cores with the driver
    driver = SimDriver(
        SafetyLimits.from_cell(CELL), q_home=HOME, options=DriverOptions(stale_state_s=1.0, watchdog_s=1.0)
    )
    driver.connect()
    captures: list[int] = []
    capture = source.capture

    def counted() -> RGBDFrame:
        captures.append(1)
        return capture()

    source.capture = counted  # type: ignore[method-assign]
    try:
        watch = CellWatch(
            CELL,
            spec,
            lambda z: np.asarray(SENSOR.depth_rms_m(z, source.camera.fx)),
            stream=open_stream,
            acknowledge=lambda message: asked.append(message) or True,
            on_event=lambda event: stopped.append(event.requested_at),
            clear_frames=5,
            max_gap_s=3.0,  # the synthetic 640x480 stream runs at a few fps on a loaded 2-core machine
        )
        records = run_cell_loop(
            CELL, source, source.ground_truth_segmenter(), default_part_library(), driver, execute=True,
            max_picks=2, watch=watch,
        )  # fmt: skip
    finally:
        for s in opened:
            s.close()
        driver.disconnect()
        driver.shutdown()
    assert [r.status for r in records] == ["zone_stop", "picked"], [(r.status, r.fault) for r in records]
    assert "hand in zone 'bin'" in records[0].fault and len(asked) == 1 and "acknowledge" in asked[0]
    assert len(captures) == 2 and len(opened) == 2  # re-captured and re-planned: a second plan, a second watch
    assert records[1].start_q is not None and np.max(np.abs(records[1].start_q - HOME)) > 1e-3  # from where it stopped
    assert watch.events[0].intrusions[0]["label"] == "hand"


def test_run_refuses_a_missing_static_reference_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import yaml

    from normpos_grasp.cli.main import main

    data = _cell_dict()
    data["templates"] = str(CELL_YAML.parent / data["templates"])
    data["watch"] = {"zones": [{"name": "bin", "min": [0.28, -0.17, 0.0], "max": [0.72, 0.17, 0.5]}],
                     "static_reference": "missing.reference.json"}  # fmt: skip
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code = main(["run", "--cell", str(cell_file), "--source", "synthetic:1", "--robot", "sim", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "missing.reference.json" in err[0]
    assert not (out / "run.json").exists()  # refused before the first turn
