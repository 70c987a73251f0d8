"""The zone watch stops a real ur_rtde motion on the loopback UR controller; the controller records the stop.

The real ur_rtde client (RtdeDriver) runs a moveJ, and a servoJ stream, while a 30 fps synthetic depth stream
(normpos_grasp.watch.synthetic: the cell's static scene, the arm at its measured joints, D435 noise; its fast
model, so that the renderer, which shares this process, takes little of the GIL and the cores) is checked by
the ZoneWatch thread; a hand-sized box appears in the bin part-way through. The controller's own record
(`emu since T`) says which stop command arrived and when. No timing assertions (the machine is shared): the
latencies are printed; benchmarks/bench_watch.py reports them.
"""

from __future__ import annotations

import functools
import logging
import os
import time
from collections.abc import Iterator

import numpy as np
import pytest
import rtde_control  # noqa: F401  (a hard dependency: imported, never skipped)

from normpos_grasp.cell import resolve_cell
from normpos_grasp.cell.config import WatchSpec, ZoneSpec
from normpos_grasp.errors import DriverFault, ZoneIntrusion
from normpos_grasp.execution import DriverOptions, RtdeDriver, SafetyLimits
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.sim.cameras import camera_intrinsics
from normpos_grasp.sim.sensor import sensor_preset
from normpos_grasp.sim.ur_emulator import EmulatorProcess
from normpos_grasp.watch.expected import ExpectedScene
from normpos_grasp.watch.intrusion import IntrusionDetector
from normpos_grasp.watch.monitor import ZoneWatch
from normpos_grasp.watch.synthetic import SyntheticCellStream, ThreadedStream, cell_background, hand_box

HOST = f"127.{100 + os.getpid() % 100}.{os.getpid() // 100 % 250 + 1}.9"
CELL = resolve_cell("ur5e_bin_parallel")
HOME = np.asarray(CELL.home_q, dtype=np.float64)
SPEC = WatchSpec(zones=(ZoneSpec("bin", np.array([0.28, -0.17, 0.0]), np.array([0.72, 0.17, 0.5])),), downsample=1)
HAND_AT = np.array([0.42, -0.1, 0.12])


def _since(emu: EmulatorProcess, t: float) -> dict[str, str]:
    reply = emu.emu("since", f"{t:.6f}")
    return dict(part.split("=", 1) for part in reply.split()[2:] if "=" in part)


@pytest.fixture(scope="module")
def emu(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EmulatorProcess]:
    log = tmp_path_factory.mktemp("emu") / "emulator.log"
    with EmulatorProcess(HOST, "ur5e", ready_timeout_s=60.0, log_path=log) as proc:
        proc.emu("unlock_delay", "0.5")
        yield proc


@pytest.fixture(scope="module")
def driver(emu: EmulatorProcess) -> Iterator[RtdeDriver]:
    drv = RtdeDriver(HOST, SafetyLimits.for_model("ur5e"), options=DriverOptions(stale_state_s=1.0))
    drv.connect()
    yield drv
    drv.disconnect()


@functools.cache
def _scene() -> SyntheticCellStream:
    """The synthetic cell, built once for the module."""
    camera = camera_intrinsics("d435", (320, 240)).with_extrinsics(CELL.world_from_camera)
    arm = ArmModel.from_name("ur5e", CELL.world_from_base)
    background, _ = cell_background(CELL, camera, 4, seed=3)
    return SyntheticCellStream(camera, background, arm, CELL.tool, sensor_preset("d435"), seed=4, fast=True)


def _watch(driver: RtdeDriver, protective: bool, appear_s: float) -> tuple[ZoneWatch, ThreadedStream]:
    scene = _scene()
    camera, arm, sensor = scene.camera, scene.arm, sensor_preset("d435")
    q0 = driver.state().q
    expected = ExpectedScene(
        camera,
        scene.frame(q0),
        lambda z: np.asarray(sensor.depth_rms_m(z, camera.fx)),
        arm,
        CELL.tool,
        downsample=1,
        q_capture=q0,
        static_boxes=CELL.static_boxes,
    )
    hand = hand_box(HAND_AT)
    stream = ThreadedStream(scene, lambda: driver.state().q, lambda t: [hand] if t >= appear_s else [], 30.0)
    watch = ZoneWatch(
        IntrusionDetector.from_spec(expected, SPEC),
        stream,
        driver,
        protective=protective,
        q_source=lambda: driver.state().q,
        max_gap_s=5.0,
    )
    return watch, stream


def _recover(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    deadline = time.monotonic() + 20.0
    while True:
        emu.dashboard("unlock protective stop")
        try:
            driver.resume()
            break
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.3)
    driver.move_joints([HOME], 1.0, 2.0)


def _first_intruder_frame(stream: ThreadedStream) -> float:
    assert stream.first_seen, "the stream never showed the intruder"
    return min(stream.first_seen.values())


def test_intrusion_during_movej_stops_the_arm(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    target = HOME + np.array([0.6, 0.15, -0.2, 0.0, 0.0, 0.4])
    watch, stream = _watch(driver, protective=False, appear_s=0.6)
    stream.start()
    with watch, pytest.raises(ZoneIntrusion) as err:
        driver.move_joints([target], 0.4, 1.0)
    stream.close()
    shown = _first_intruder_frame(stream)
    info = _since(emu, shown)
    detail = err.value.detail
    assert detail["stop_kind"] == "stop" and detail["intrusions"][0]["zone"] == "bin"
    assert info["stop"] == "stopJ" and float(info["stop_t"]) >= shown
    assert int(info["motion_after_stop"]) == 0
    st = driver.state()
    assert float(np.max(np.abs(st.qd))) < 1e-6 and float(np.max(np.abs(st.q - target))) > 0.05  # stopped short
    logging.getLogger(__name__).info(
        "moveJ: stopJ %.1f ms after the first frame showing the hand", (float(info["stop_t"]) - shown) * 1e3
    )
    with pytest.raises(DriverFault, match="halted by ZoneIntrusion"):  # latched: nothing is sent until resume()
        driver.move_joints([HOME], 1.0, 2.0)
    _recover(driver, emu)


def test_intrusion_during_servo_stream_protective_stop(driver: RtdeDriver, emu: EmulatorProcess) -> None:
    q0 = driver.state().q
    t = np.linspace(0.0, 3.0, 151)
    s = 0.5 - 0.5 * np.cos(np.pi * t / 3.0)
    q = q0[None] + s[:, None] * np.array([0.5, 0.1, -0.15, 0.0, 0.0, 0.3])[None]
    watch, stream = _watch(driver, protective=True, appear_s=0.8)
    stream.start()
    with watch, pytest.raises(ZoneIntrusion) as err:
        driver.follow_trajectory(t, q)
    stream.close()
    shown = _first_intruder_frame(stream)
    info = _since(emu, shown)
    assert err.value.detail["stop_kind"] == "protective"
    assert info["stop"] == "triggerProtectiveStop" and float(info["stop_t"]) >= shown
    assert int(info["motion_after_stop"]) == 0
    assert driver.state().protective_stopped
    logging.getLogger(__name__).info(
        "servoJ: protective stop %.1f ms after the first frame", (float(info["stop_t"]) - shown) * 1e3
    )
    _recover(driver, emu)
