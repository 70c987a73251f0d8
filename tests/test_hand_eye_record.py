"""`calibrate hand-eye --record HOST`: flange poses recorded over RTDE with the unmodified ur_rtde client from the
loopback UR controller, which is moved between the poses by ur_rtde's control interface."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from loopback import loopback_host

from normpos_grasp.camera.hand_eye_io import read_poses_csv
from normpos_grasp.cli.calibrate_hand_eye import record_poses
from normpos_grasp.errors import InputError
from normpos_grasp.sim.ur_emulator import EmulatorProcess

HOST = loopback_host(71)  # one emulator per address; this one is used by no other test


@pytest.fixture(scope="module")
def emu(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EmulatorProcess]:
    log = tmp_path_factory.mktemp("emu") / "emulator.log"
    with EmulatorProcess(HOST, "ur5e", ready_timeout_s=60.0, log_path=log) as proc:
        yield proc


def test_record_poses_over_rtde(emu: EmulatorProcess, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import rtde_control
    import rtde_receive

    control = rtde_control.RTDEControlInterface(HOST)
    receive = rtde_receive.RTDEReceiveInterface(HOST)
    try:
        q0 = np.array(receive.getActualQ())
        wrist = [[0.3, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.5], [-0.2, 0.2, 0.3]]
        targets = [q0 + np.r_[0.0, 0.0, 0.0, d] for d in wrist]
        truth: list[list[float]] = []
        actions = iter(["move 0", "async 1", "settle", "move 2", "move 3", "quit"])

        def settle() -> None:
            deadline = time.monotonic() + 5.0
            while np.abs(receive.getActualQd()).max() > 1e-5 and time.monotonic() < deadline:
                time.sleep(0.02)
            truth.append(list(receive.getActualTCPPose()))

        def operator(_: str) -> str:
            """Moves the arm and presses Enter; once, Enter comes while the arm still moves."""
            verb, *arg = next(actions).split()
            if verb == "quit":
                return "q"
            if verb == "async":
                assert control.moveJ(targets[int(arg[0])].tolist(), 1.0, 1.0, True)
                time.sleep(0.05)
                return ""
            if verb == "move":
                assert control.moveJ(targets[int(arg[0])].tolist(), 1.0, 2.0)
            settle()
            return ""

        path = tmp_path / "POSES.csv"
        poses = record_poses(HOST, path, "eye-in-hand", prompt=operator)
    finally:
        control.stopScript()
        control.disconnect()
        receive.disconnect()
    printed = capsys.readouterr().out
    assert "the arm is moving" in printed and "rotation spread" in printed
    assert f"recorded {len(truth)} poses" in printed
    np.testing.assert_allclose(poses, truth, atol=1e-6)
    np.testing.assert_allclose(read_poses_csv(path), truth, atol=1e-8)
    assert np.ptp(poses[:, 3:], axis=0).max() > 0.1  # the wrist really turned between the poses
    with pytest.raises(InputError, match="already exists"):
        record_poses(HOST, path, "eye-in-hand", prompt=lambda _: "q")
