"""Robotiq URCap socket: commanded openings against the simulated fingers, grip detection, ur_rtde's own client.

Protocol: for each model (2F-85, 2F-140) the emulator's simulated gripper (sim/ur_emulator/robotiq_server.py) is
served on a free 127.0.0.1 port and driven by `execution.robotiq.RobotiqGripper` (activation with the ends
calibrated, then `--openings` random openings across the stroke, seeded): the error is the simulated fingers'
opening minus the commanded one (max and median, mm), with the time of each `open()` (median, s, fingers at full
speed). Then `--picks` closes on nothing (OBJ must be 3, grip not detected) and `--picks` closes on a part of random
width (OBJ must be 2, width error of the stopped fingers). With `--urrtde` the unmodified C++ RobotiqGripper
of the installed ur_rtde wheel (tests/fixtures/robotiq/urrtde_robotiq_probe.cpp, compiled with g++) activates,
auto-calibrates, moves and closes on nothing and on a part. The machine's load average is printed with the figures.

    nice -n 10 .venv/bin/python benchmarks/bench_robotiq.py [--openings 200] [--picks 20] [--seed 0] [--urrtde]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from normpos_grasp.cell.gripper_driver import RobotiqDriverSpec
from normpos_grasp.execution.robotiq import RobotiqGripper
from normpos_grasp.sim.ur_emulator.robotiq_server import ROBOTIQ_MODELS, RobotiqServer, SimulatedRobotiq

HOST = "127.0.0.1"
PROBE = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "robotiq" / "urrtde_robotiq_probe.cpp"


def bench_model(name: str, openings: int, picks: int, rng: np.random.Generator) -> None:
    model = ROBOTIQ_MODELS[name]
    sim = SimulatedRobotiq(model)
    with RobotiqServer(sim, HOST, 0) as server:
        spec = RobotiqDriverSpec(model=name, stroke_m=model.stroke_m, port=server.port, calibrate=True)
        client = RobotiqGripper(HOST, spec)
        t0 = time.perf_counter()
        client.connect()
        t_connect = time.perf_counter() - t0
        errors, times = [], []
        for opening in rng.uniform(0.0, model.stroke_m, openings):
            t0 = time.perf_counter()
            client.open(float(opening))
            times.append(time.perf_counter() - t0)
            errors.append(abs(model.opening_at(sim.pos) - opening))
        nothing = 0
        for _ in range(picks):
            client.open(model.stroke_m)
            st = client.close()
            nothing += int(st.obj == 3 and not client.grip_detected())
        caught, width_err = 0, []
        for width in rng.uniform(0.1 * model.stroke_m, 0.9 * model.stroke_m, picks):
            sim.set_part(float(width))
            client.open(model.stroke_m)
            st = client.close()
            caught += int(st.obj == 2 and client.grip_detected())
            width_err.append(abs(st.opening_m - width))
            sim.set_part(None)
        client.disconnect()
    e = np.asarray(errors) * 1e3
    print(
        f"{name}: activate+calibrate {t_connect:.2f} s (ends {client.open_counts}/{client.closed_counts}); "
        f"{openings} openings: error max {e.max():.3f} mm, median {np.median(e):.3f} mm (goal < 1 mm); "
        f"open() median {np.median(times):.3f} s"
    )
    w = np.asarray(width_err) * 1e3
    print(
        f"{name}: pick on nothing -> OBJ 3, no grip: {nothing}/{picks}; pick on a part -> OBJ 2, grip: "
        f"{caught}/{picks}, stopped-finger width error max {w.max():.3f} mm"
    )


def bench_urrtde() -> None:
    import rtde_control

    compiler = shutil.which("g++")
    if compiler is None:
        print("ur_rtde client: skipped (no g++)")
        return
    lib_dir = Path(rtde_control.__file__).resolve().parent
    lib = next(lib_dir.glob("librtde.so.1.6*"))
    with tempfile.TemporaryDirectory() as tmp:
        exe = Path(tmp) / "probe"
        cmd = [compiler, "-std=c++17", "-O1", "-D_GLIBCXX_USE_CXX11_ABI=0", str(PROBE), "-o", str(exe), str(lib)]
        subprocess.run([*cmd, f"-Wl,-rpath,{lib_dir}"], check=True, capture_output=True)
        model = ROBOTIQ_MODELS["2F-85"]
        sim = SimulatedRobotiq(model)
        with RobotiqServer(sim, HOST, 0) as server:
            for label, width in (("nothing", None), ("part 30 mm", 0.030)):
                sim.set_part(width)
                t0 = time.perf_counter()
                done = subprocess.run([str(exe), HOST, str(server.port), "120"], capture_output=True, text=True)
                lines = [ln[7:] for ln in done.stdout.splitlines() if ln.startswith("RESULT ")]
                print(
                    f"ur_rtde RobotiqGripper ({label}): exit {done.returncode} in {time.perf_counter() - t0:.1f} s; "
                    + "; ".join(lines)
                )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--openings", type=int, default=200)
    ap.add_argument("--picks", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--urrtde", action="store_true", help="also drive it with ur_rtde's C++ client (needs g++)")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    load0 = os.getloadavg()[0]
    for name in ROBOTIQ_MODELS:
        bench_model(name, args.openings, args.picks, rng)
    if args.urrtde:
        bench_urrtde()
    print(f"load average {load0:.1f} -> {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
