"""The Robotiq URCap socket: the emulator's simulated 2F gripper (robotiq_server) driven by this package's client
(execution.robotiq) and by ur_rtde's own, unmodified C++ RobotiqGripper client from the installed wheel."""

from __future__ import annotations

import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from normpos_grasp.cell.gripper_driver import RobotiqDriverSpec
from normpos_grasp.errors import GripperFault, InputError
from normpos_grasp.execution.robotiq import OBJ_AT_POSITION, OBJ_CONTACT_CLOSING, RobotiqGripper, RobotiqSocket
from normpos_grasp.sim.ur_emulator.robotiq_server import ROBOTIQ_MODELS, RobotiqModel, RobotiqServer, SimulatedRobotiq

HOST = "127.0.0.1"  # every server here binds port 0 (a free port): the tests run in parallel


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(params=["2F-85", "2F-140"])
def served(request: pytest.FixtureRequest) -> Iterator[tuple[SimulatedRobotiq, RobotiqGripper]]:
    model = ROBOTIQ_MODELS[request.param]
    sim = SimulatedRobotiq(model)
    with RobotiqServer(sim, HOST, 0) as server:
        spec = RobotiqDriverSpec(model=model.name, stroke_m=model.stroke_m, port=server.port, calibrate=True)
        client = RobotiqGripper(HOST, spec)
        client.connect()
        yield sim, client
        client.disconnect()


def test_calibrated_client_commands_openings_within_1_mm(served: tuple[SimulatedRobotiq, RobotiqGripper]) -> None:
    sim, client = served
    m = sim.model
    assert (client.open_counts, client.closed_counts) == (m.open_counts, m.closed_counts)  # measured at activation
    rng = np.random.default_rng(3)
    for opening in [0.0, m.stroke_m, *rng.uniform(0.0, m.stroke_m, 4)]:
        st = client.open(float(opening))
        assert st.obj == OBJ_AT_POSITION
        finger_opening = m.opening_at(sim.pos)  # where the simulated fingers are, not what the client computes
        assert abs(finger_opening - opening) < 1e-3, (opening, finger_opening)
        assert abs(st.opening_m - finger_opening) < 1e-9


def test_pick_on_nothing_reports_no_object_and_a_part_stops_the_fingers(
    served: tuple[SimulatedRobotiq, RobotiqGripper],
) -> None:
    sim, client = served
    client.open(0.05)
    st = client.close()
    assert st.obj == OBJ_AT_POSITION and st.position == sim.model.closed_counts
    assert client.grip_detected() is False
    sim.set_part(0.031)
    client.open(0.05)
    st = client.close()
    assert st.obj == OBJ_CONTACT_CLOSING
    assert abs(st.opening_m - 0.031) < 1e-3
    assert client.grip_detected() is True
    client.open(0.05)  # wider than the part: released
    assert sim.held is None


def test_fingers_move_at_the_commanded_speed() -> None:
    clock = FakeClock()
    model = ROBOTIQ_MODELS["2F-85"]
    sim = SimulatedRobotiq(model, clock=clock)
    assert sim.handle_line("SET ACT 1") == "ack"
    clock.t += model.activation_s + 1e-3
    assert sim.handle_line("GET STA") == "STA 3\n"
    for spe, speed in ((255, model.speed_max_m_s), (0, model.speed_min_m_s)):
        start = model.counts_at(model.stroke_m)
        sim.pos = start
        assert sim.handle_line(f"SET POS 255 SPE {spe} FOR 10 GTO 1") == "ack"
        clock.t += 0.1
        sim.advance()
        travelled = model.opening_at(start) - model.opening_at(sim.pos)
        assert travelled == pytest.approx(speed * 0.1, rel=1e-6)
        assert sim.handle_line("GET OBJ") == "OBJ 0\n"  # still moving
        assert sim.handle_line("SET GTO 0") == "ack"


def test_protocol_replies_as_the_urcap() -> None:
    sim = SimulatedRobotiq(ROBOTIQ_MODELS["2F-85"])
    with RobotiqServer(sim, HOST, 0) as server, socket.create_connection((HOST, server.port), timeout=2) as sock:
        sock.sendall(b"SET ACT 1 ATR 0\n")
        assert sock.recv(64) == b"ack"  # no line end, as ur_rtde's clients compare it
        sock.sendall(b"GET ACT\nGET FLT\n")  # two requests in one packet: both answers in one packet
        reply = b""
        while reply.count(b"\n") < 2:
            reply += sock.recv(64)
        assert reply == b"ACT 1\nFLT 0\n"
        for bad in (b"SET POS 256\n", b"SET XYZ 1\n", b"JUMP\n", b"SET POS\n"):
            sock.sendall(bad)
            assert sock.recv(64) == b"?", bad


def test_missing_urcap_is_a_typed_error_in_one_line() -> None:
    with socket.socket() as probe:
        probe.bind((HOST, 0))
        port = probe.getsockname()[1]  # bound, not listening: refused
        client = RobotiqGripper(HOST, RobotiqDriverSpec(port=port))
        with pytest.raises(GripperFault, match="URCap installed") as err:
            client.connect()
    assert "\n" not in str(err.value)


def test_silent_socket_times_out_within_the_reply_bound() -> None:
    with socket.socket() as lst:
        lst.bind((HOST, 0))
        lst.listen(1)  # accepts, never answers
        link = RobotiqSocket(HOST, lst.getsockname()[1], reply_timeout_s=0.3)
        link.connect()
        t0 = time.monotonic()
        with pytest.raises(GripperFault, match="did not answer"):
            link.get("STA")
        assert time.monotonic() - t0 < 1.0


def test_activation_timeout_and_faults_are_gripper_faults() -> None:
    slow = RobotiqModel("2F-85", 0.085, 0.02, 0.15, activation_s=30.0)
    sim = SimulatedRobotiq(slow)
    with RobotiqServer(sim, HOST, 0) as server:
        client = RobotiqGripper(HOST, RobotiqDriverSpec(port=server.port, activation_timeout_s=0.3))
        t0 = time.monotonic()
        with pytest.raises(GripperFault, match="did not activate within 0.3 s"):
            client.connect()
        assert time.monotonic() - t0 < 1.5
        client.disconnect()
    sim = SimulatedRobotiq(ROBOTIQ_MODELS["2F-85"])
    with RobotiqServer(sim, HOST, 0) as server:
        client = RobotiqGripper(HOST, RobotiqDriverSpec(port=server.port))
        client.connect()
        sim.inject_fault(0x0E)
        with pytest.raises(GripperFault, match="0x0E .overcurrent") as err:
            client.close()
        assert err.value.detail == 0x0E
        with pytest.raises(InputError, match="outside the 2F-85's stroke"):
            client.open(0.09)
        client.disconnect()


def test_a_move_that_never_ends_times_out() -> None:
    sim = SimulatedRobotiq(RobotiqModel("2F-140", 0.14, 0.0001, 0.0002))  # fingers at 0.2 mm/s
    with RobotiqServer(sim, HOST, 0) as server:
        client = RobotiqGripper(HOST, RobotiqDriverSpec("2F-140", 0.14, port=server.port, move_timeout_s=0.3))
        client.connect()
        with pytest.raises(GripperFault, match="did not reach position 255 within 0.3 s"):
            client.close()
        client.disconnect()


# ---------------------------------------------------------------------- ur_rtde's own Robotiq client
PROBE_SOURCE = Path(__file__).parent / "fixtures" / "robotiq" / "urrtde_robotiq_probe.cpp"


@pytest.fixture(scope="module")
def urrtde_probe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """ur_rtde 1.6.5's C++ RobotiqGripper (in the wheel's librtde.so; the wheel has no Python binding for it)."""
    import rtde_control

    compiler = shutil.which("g++")
    if compiler is None:
        pytest.skip("no C++ compiler: ur_rtde's Robotiq client is only reachable from C++")
    lib_dir = Path(rtde_control.__file__).resolve().parent
    lib = next(lib_dir.glob("librtde.so.1.6*"), None)
    assert lib is not None, f"librtde.so not found next to {rtde_control.__file__}"
    exe = tmp_path_factory.mktemp("probe") / "urrtde_robotiq_probe"
    cmd = [compiler, "-std=c++17", "-O1", "-D_GLIBCXX_USE_CXX11_ABI=0", str(PROBE_SOURCE), "-o", str(exe), str(lib)]
    subprocess.run([*cmd, f"-Wl,-rpath,{lib_dir}"], check=True, capture_output=True, timeout=120)
    return exe


def _run_probe(exe: Path, port: int, target: int) -> dict[str, list[int]]:
    done = subprocess.run([str(exe), HOST, str(port), str(target)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    results = {}
    for line in done.stdout.splitlines():
        if line.startswith("RESULT "):
            key, *values = line.split()[1:]
            results[key] = [int(v) for v in values]
    return results


def test_urrtde_robotiq_client_drives_the_loopback_gripper(urrtde_probe: Path) -> None:
    model = ROBOTIQ_MODELS["2F-85"]
    sim = SimulatedRobotiq(model)
    with RobotiqServer(sim, HOST, 0) as server:
        empty = _run_probe(urrtde_probe, server.port, 120)
        assert empty["calibrated"] == [model.open_counts, model.closed_counts]  # ur_rtde's auto-calibration
        assert empty["move"] == [3, 120]  # AT_DEST at the commanded position
        assert empty["close"] == [3, model.closed_counts]  # closed on nothing: AT_DEST, no object
        sim.set_part(0.030)
        caught = _run_probe(urrtde_probe, server.port, 60)
        status, position = caught["close"]
        assert status == 2  # STOPPED_INNER_OBJECT: the part stopped the fingers
        assert abs(model.opening_at(position) - 0.030) < 1e-3


def test_a_held_part_follows_the_tcp_and_stays_where_released() -> None:
    tcp = np.array([0.5, 0.0, 0.2])
    lock = threading.Lock()

    def where() -> np.ndarray:
        with lock:
            return tcp.copy()

    sim = SimulatedRobotiq(ROBOTIQ_MODELS["2F-85"], tcp_position=where)
    with RobotiqServer(sim, HOST, 0) as server:
        client = RobotiqGripper(HOST, RobotiqDriverSpec(port=server.port, open_counts=3, closed_counts=229))
        client.connect()
        sim.set_part(0.03, np.array([0.5, 0.0, 0.2]), radius_m=0.01)
        with lock:
            tcp[:] = (0.3, 0.0, 0.2)  # away from the part: a pick on nothing
        client.open(0.05)
        assert client.close().obj == OBJ_AT_POSITION
        with lock:
            tcp[:] = (0.5, 0.0, 0.2)
        client.open(0.05)
        assert client.close().obj == OBJ_CONTACT_CLOSING
        with lock:
            tcp[:] = (0.0, -0.45, 0.1)  # carried to the place
        client.open(0.05)
        part = sim.parts[0]
        assert part.position is not None and np.allclose(part.position, (0.0, -0.45, 0.1))
        client.disconnect()
