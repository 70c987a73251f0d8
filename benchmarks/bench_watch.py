"""Zone watch and per-frame drift check (issue 22): intrusions caught, false stops, stop latency, bumped cameras.

Scenario: the packaged ur5e_bin_parallel cell, its camera at 320x240 (D435 intrinsics scaled, D435 noise model of
normpos_grasp.sim.sensor at that focal length), a bin with six part-sized boxes, the arm running a pick cycle (home
-> above the bin -> grasp -> above the bin -> out of view towards the place -> home, joint-space moves at up to 2
rad/s). Watched: the bin (to 0.5 m), an operator-side strip, and a 10 cm band around the arm; margin 2 cm; the
detector's approach band (13 cm around each zone box, docs/watch.md) on, as by default.

1. Intrusions (--trials, half hand-sized boxes at 2.0 m/s, half person-sized shapes at 1.6 m/s: ISO 13855's
   approach speeds), entering a zone at a random time of the cycle from a random side. Frames at 30 fps, each
   checked when it arrives, the silhouette covering the arm's poses of the last `latency_s`. "First appears": the
   first frame in which the intruder is visible and inside a zone. Reported: caught (within 1 s), frames late,
   check time (ms, this machine), and the decision latency = frames late x 33.3 ms + the check time of the frame
   that caught it (the driver sends the stop at its next state poll: <= 8 ms; the loopback-controller section
   measures that end to end).
2. False stops (--cycles without intrusion, --frames-per-cycle frames at random times of each cycle, a part
   swinging in the gripper by up to 20 deg after the grasp).
3. End to end on the loopback UR controller (--emulator N, 0 to skip): the real ur_rtde client (RtdeDriver) runs a
   moveJ while a 30 fps synthetic stream (fast sensor model, rendered in this process) shows the arm at its measured
   joints; a hand appears in the bin at a random time; the controller records when stopJ arrived. Latency: stop
   arrival - arrival of the first frame showing it, split into its steps.
4. Drift: a textured plate at the cell's table seen by a 640x480 camera with D435 RGB noise; --drift-trials bumps of
   2 mm (random direction) and 0.2 deg (random axis) each, and --still-frames unmoved frames.

    .venv/bin/python benchmarks/bench_watch.py [--trials 200] [--cycles 1000] [--frames-per-cycle 6]
        [--emulator 10] [--drift-trials 100] [--still-frames 1000] [--seed 0]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from normpos_grasp.cell import resolve_cell
from normpos_grasp.cell.config import WatchSpec, ZoneSpec
from normpos_grasp.geometry.transforms import invert_pose
from normpos_grasp.kinematics.arm import ArmModel
from normpos_grasp.sim.cameras import camera_intrinsics
from normpos_grasp.sim.sensor import sensor_preset
from normpos_grasp.watch.expected import ExpectedScene, joint_path
from normpos_grasp.watch.intrusion import IntrusionDetector
from normpos_grasp.watch.synthetic import Intruder, SyntheticCellStream, cell_background, hand_box, person_shape
from normpos_grasp.watch.zones import WatchZones

FPS = 30.0


def load() -> str:
    return " / ".join(f"{v:.2f}" for v in os.getloadavg())


def watch_spec() -> WatchSpec:
    zones = (
        ZoneSpec("bin", np.array([0.28, -0.17, 0.0]), np.array([0.72, 0.17, 0.5])),
        ZoneSpec("operator_side", np.array([0.74, -0.45, 0.0]), np.array([0.95, 0.45, 0.6])),
    )
    return WatchSpec(zones=zones, margin_m=0.02, arm_margin_m=0.1, downsample=1, min_blob_px=12)


def tool_down(arm: ArmModel, cell: object, xyz: tuple[float, float, float], q_ref: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = xyz
    flange = pose @ invert_pose(cell.tool.flange_from_tcp)  # type: ignore[attr-defined]
    qs, ok = arm.ik(flange[None], q_ref)
    cands = qs[0][ok[0]]
    return np.asarray(cands[np.argmin(np.abs(cands - q_ref).max(axis=1))])


class Cycle:
    """A pick cycle: joint waypoints, each move a cosine-profiled joint interpolation at <= 2 rad/s."""

    def __init__(self, cell: object, arm: ArmModel) -> None:
        home = np.asarray(cell.home_q, dtype=np.float64)  # type: ignore[attr-defined]
        above = tool_down(arm, cell, (0.5, 0.0, 0.35), home)
        grasp = tool_down(arm, cell, (0.5, 0.02, 0.09), above)
        place = tool_down(arm, cell, (0.0, -0.45, 0.15), above)
        self.wps = [home, above, grasp, above, place, home]
        self.grasp_index = 2
        self.times = [0.0]
        for a, b in zip(self.wps[:-1], self.wps[1:], strict=True):
            self.times.append(self.times[-1] + max(0.4, 1.6 * float(np.max(np.abs(b - a))) / 2.0))
        self.duration = self.times[-1]

    def q(self, t: float) -> np.ndarray:
        t = float(np.clip(t, 0.0, self.duration))
        i = min(int(np.searchsorted(self.times, t, side="right")) - 1, len(self.wps) - 2)
        s = (t - self.times[i]) / (self.times[i + 1] - self.times[i])
        s = 0.5 - 0.5 * np.cos(np.pi * s)
        return np.asarray(self.wps[i] + s * (self.wps[i + 1] - self.wps[i]))

    def holding(self, t: float) -> bool:
        return self.times[self.grasp_index] <= t <= self.times[-2]


class Bench:
    def __init__(self, seed: int) -> None:
        self.cell = resolve_cell("ur5e_bin_parallel")
        self.camera = camera_intrinsics("d435", (320, 240)).with_extrinsics(self.cell.world_from_camera)
        self.arm = ArmModel.from_name("ur5e", self.cell.world_from_base)
        self.sensor = sensor_preset("d435")
        self.spec = watch_spec()
        self.background, _ = cell_background(self.cell, self.camera, 6, seed)
        self.scene = SyntheticCellStream(self.camera, self.background, self.arm, self.cell.tool, self.sensor, seed)
        self.cycle = Cycle(self.cell, self.arm)
        self.zones = WatchZones.from_spec(self.spec)
        self.rng = np.random.default_rng(seed + 1)
        self.held_radius = 0.09  # the held part (<= 6 cm from the TCP) and its swing

    def sigma(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(self.sensor.depth_rms_m(z, self.camera.fx))

    def detector(self) -> IntrusionDetector:
        """The watch period's expected scene from a fresh measurement with the arm at home."""
        reference = self.scene.frame(self.cycle.q(0.0))
        expected = ExpectedScene(
            self.camera,
            reference,
            self.sigma,
            self.arm,
            self.cell.tool,
            downsample=self.spec.downsample,
            k_sigma=self.spec.k_sigma,
            pad_m=self.spec.silhouette_pad_m,
            q_capture=self.cycle.q(0.0),
            static_boxes=self.cell.static_boxes,
        )
        return IntrusionDetector.from_spec(expected, self.spec)

    def held_part(self, t: float) -> list[Intruder]:
        """The held part: a 6 cm capsule hanging below the TCP, swinging by up to 20 deg."""
        if not self.cycle.holding(t):
            return []
        flange = self.arm.fk(self.cycle.q(t))
        tcp = flange @ self.cell.tool.flange_from_tcp
        swing = np.radians(20.0) * np.sin(2 * np.pi * 1.3 * t)
        d = tcp[:3, :3] @ np.array([np.sin(swing), 0.0, np.cos(swing)])
        a = tcp[:3, 3] + 0.01 * d
        return [Intruder((), ((a, a + 0.05 * d, 0.025),))]

    def check(self, det: IntrusionDetector, t_frame: float, depth: np.ndarray) -> tuple[bool, float, float]:
        """Check a frame exposed at t_frame, arriving one frame later; the watch reads joints at 30 Hz. Returns
        (intrusion, wall-clock ms, CPU ms of the check)."""
        t_now = t_frame + 1.0 / FPS
        history = [(t, self.cycle.q(t)) for t in np.arange(t_now - 0.2, t_now + 1e-9, 1.0 / FPS)]
        path = joint_path(history, t_now - self.spec.latency_s)
        held = self.held_radius if self.cycle.holding(t_frame) or self.cycle.holding(t_now) else 0.0
        res = det.check(depth, path, held)
        return (not res.clear), res.elapsed_ms, res.cpu_ms


def intruder_path(b: Bench, kind: str) -> tuple[Intruder, np.ndarray, np.ndarray]:
    """(shape at its start, start offset, velocity (3,)): enters a zone from outside at the ISO 13855 speed."""
    rng = b.rng
    if kind == "hand":
        target = np.array([rng.uniform(0.35, 0.65), rng.uniform(-0.1, 0.1), rng.uniform(0.05, 0.3)])
        ang = rng.uniform(0, 2 * np.pi)
        d = np.array([np.cos(ang), np.sin(ang), 0.0])
        start = target + 0.45 * d + np.array([0.0, 0.0, rng.uniform(0.0, 0.15)])
        speed = 2.0
        shape = hand_box(np.zeros(3))
    else:
        target = np.array([rng.uniform(0.78, 0.85), rng.uniform(-0.3, 0.3), rng.uniform(0.3, 0.45)])
        start = target + np.array([0.6, rng.uniform(-0.2, 0.2), 0.0])
        speed = 1.6
        shape = person_shape(np.zeros(3), np.array([-1.0, 0.0, 0.0]))
    vel = (target - start) / np.linalg.norm(target - start) * speed
    return shape, start, vel


def intrusion_trials(b: Bench, trials: int) -> None:
    caught, late, latency, latency_cpu, ms, cpu, labels = 0, [], [], [], [], [], {"person": 0, "hand": 0}
    missed, late_trials, late_measured, latency_measured = [], [], [], []
    for k in range(trials):
        kind = "hand" if k % 2 == 0 else "person"
        det = b.detector()
        shape, start, vel = intruder_path(b, kind)
        t_enter = b.rng.uniform(0.3, b.cycle.duration - 1.2)
        arrive = float(np.linalg.norm(vel) ** -1 * 0.0)
        first = None
        measured = None  # the first frame with >= min_blob_px of the intruder measured (valid depth) in a zone
        hit = None
        for f in range(int(2.5 * FPS)):
            t = t_enter + f / FPS
            pos = start + vel * min(f / FPS, np.linalg.norm(start - start) + 1e9)
            dist_to_go = None
            it = shape.moved(pos)
            # stop at the target (the intruder stays)
            travel = np.linalg.norm(vel) * f / FPS
            total = 0.6 if kind == "person" else 0.45
            if travel > total + 0.15:
                it = shape.moved(start + vel / np.linalg.norm(vel) * (total + 0.15))
            q = b.cycle.q(t)
            extra = b.held_part(t)
            truth = b.scene.truth(q, [*extra, it])
            if first is None:
                without = b.scene.truth(q, extra)
                visible = np.count_nonzero((truth > 0) & ((without == 0) | (truth < without - 1e-4)))
                inside = (b.zones.zone_of(it.sample_points()) >= 0).any()
                if visible > 0 and inside:
                    first = f
            depth = b.scene.noisy(truth)
            if first is not None and measured is None:
                without = b.scene.truth(q, extra)
                v, u = np.nonzero((depth > 0) & (truth > 0) & ((without == 0) | (truth < without - 1e-4)))
                in_zone = b.zones.zone_of(det.expected.world_points(v, u, truth[v, u])) >= 0
                if int(in_zone.sum()) >= b.spec.min_blob_px:
                    measured = f
            tripped, t_ms, c_ms = b.check(det, t, depth)
            ms.append(t_ms)
            cpu.append(c_ms)
            if tripped:
                hit = f
                if first is None:
                    first = f  # seen in a zone before the truth test said so (the arm band): no lateness
                break
            if first is not None and f - first > FPS:
                break
            _ = arrive, dist_to_go
        if hit is not None and first is not None and hit - first <= FPS:
            caught += 1
            late.append(max(0, hit - first))
            latency.append(max(0, hit - first) * 1000.0 / FPS + ms[-1])
            latency_cpu.append(max(0, hit - first) * 1000.0 / FPS + cpu[-1])
            labels[kind] += 1
            late_measured.append(max(0, hit - (measured if measured is not None else hit)))
            latency_measured.append(late_measured[-1] * 1000.0 / FPS + cpu[-1])
            if hit > first:
                late_trials.append((k, kind, hit - first, late_measured[-1]))
        else:
            missed.append((k, kind, first, hit))
    lat = np.array(latency) if latency else np.array([np.nan])
    lat_cpu = np.array(latency_cpu) if latency_cpu else np.array([np.nan])
    print(
        f"intrusions: caught {caught}/{trials} ({100.0 * caught / trials:.1f} %; hands {labels['hand']}, persons "
        f"{labels['person']}); frames late median {np.median(late) if late else float('nan'):.0f}, max "
        f"{max(late) if late else -1}; decision latency median {np.median(lat):.1f} ms, p99 "
        f"{np.percentile(lat, 99):.1f} ms, max {lat.max():.1f} ms (with CPU time for the check: median "
        f"{np.median(lat_cpu):.1f} ms, p99 {np.percentile(lat_cpu, 99):.1f} ms); check median {np.median(ms):.2f} ms "
        f"wall, {np.median(cpu):.2f} ms CPU, max {max(ms):.2f} ms wall; load {load()}"
    )
    lat_measured = np.array(latency_measured) if latency_measured else np.array([np.nan])
    within = [float(np.mean(x <= 100.0)) * caught / trials for x in (lat, lat_cpu, lat_measured)]
    print(
        f"  stop decided <= 100 ms after the first frame: {100 * within[0]:.1f} % of trials (wall clock), "
        f"{100 * within[1]:.1f} % (check at its CPU time); frames late counted from the first frame that measures "
        f">= {b.spec.min_blob_px} px of it in a zone: median {np.median(late_measured) if late_measured else 0:.0f}, "
        f"max {max(late_measured) if late_measured else 0}; decided <= 100 ms after that frame (CPU time): "
        f"{100 * within[2]:.1f} %"
    )
    if late_trials:
        print(f"  late (trial, kind, frames late, frames late after it is measured in a zone): {late_trials[:12]}")
    if missed:
        print(f"  missed (trial, kind, first frame, caught frame): {missed[:10]}")


def false_stop_cycles(b: Bench, cycles: int, per_cycle: int) -> None:
    stops, frames, ms, cpu = 0, 0, [], []
    t0 = time.perf_counter()
    for _ in range(cycles):
        det = b.detector()
        stopped = False
        for t in np.sort(b.rng.uniform(0.0, b.cycle.duration, per_cycle)):
            depth = b.scene.frame(b.cycle.q(t), b.held_part(t))
            tripped, t_ms, c_ms = b.check(det, t, depth)
            ms.append(t_ms)
            cpu.append(c_ms)
            frames += 1
            if tripped:
                stopped = True
                break
        stops += stopped
    print(
        f"false stops: {stops} in {cycles} cycles without intrusion ({frames} frames, {per_cycle} random frames per "
        f"{b.cycle.duration:.1f} s cycle = {per_cycle / (b.cycle.duration * FPS):.2f} of its 30 fps frames); check "
        f"median {np.median(ms):.2f} ms wall, {np.median(cpu):.2f} ms CPU (p99 {np.percentile(cpu, 99):.2f} ms); "
        f"{time.perf_counter() - t0:.0f} s; load {load()}"
    )


def board_frame(camera: object, bump: np.ndarray, texture: np.ndarray, rng: np.random.Generator) -> object:
    """A textured plate on the table under the camera, seen through the camera moved by `bump`, D435 RGB noise."""
    import cv2

    from normpos_grasp.camera.model import RGBDFrame

    wfc = camera.require_world_from_camera() @ bump  # type: ignore[attr-defined]
    cfw = invert_pose(wfc)
    s = 0.6 / texture.shape[1]
    plane = np.column_stack([cfw[:3, 0], cfw[:3, 1], cfw[:3, :3] @ np.array([0.2, -0.225, 0.0]) + cfw[:3, 3]])
    h = camera.K @ plane @ np.array([[s, 0, 0.5 * s], [0, s, 0.5 * s], [0, 0, 1.0]])  # type: ignore[attr-defined]
    size = (camera.width, camera.height)  # type: ignore[attr-defined]
    gray = cv2.warpPerspective(texture, h, size, flags=cv2.INTER_LINEAR, borderValue=128).astype(np.float64)
    # D435 colour noise (normpos_grasp.sim.sensor): read noise 2 DN, shot noise 0.35 sqrt(DN)
    gray += rng.normal(0.0, 1.0, gray.shape) * np.sqrt(2.0**2 + 0.35**2 * gray)
    rgb = np.repeat(np.clip(gray + 0.5, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
    return RGBDFrame(rgb, np.zeros((size[1], size[0])), camera)  # type: ignore[arg-type]


def drift_trials(b: Bench, trials: int, still: int) -> None:
    import cv2

    from normpos_grasp.camera.calibration import ControlPoints
    from normpos_grasp.camera.static_reference import StaticReference
    from normpos_grasp.errors import CameraMoved
    from normpos_grasp.geometry import make_pose, rotation_from_rotvec
    from normpos_grasp.watch.drift import FrameDriftCheck

    rng = np.random.default_rng(7)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (450, 600)).astype(np.uint8), (0, 0), 2.0)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX)
    camera = camera_intrinsics("d435", (640, 480)).with_extrinsics(b.cell.world_from_camera)
    world = np.array([[x, y, 0.0] for x in (0.28, 0.5, 0.72) for y in (-0.16, 0.0, 0.16)])
    pixels = camera.project(world @ camera.camera_from_world[:3, :3].T + camera.camera_from_world[:3, 3])
    points = ControlPoints(tuple(f"p{i}" for i in range(len(world))), world, pixels)
    ref = StaticReference.from_calibration(camera, points, board_frame(camera, np.eye(4), texture, rng).rgb)  # type: ignore[attr-defined]
    check = FrameDriftCheck(ref, camera)
    t0 = time.perf_counter()
    false_alarms, ms, worst = 0, [], (0.0, 0.0, 0.0)
    for _ in range(still):
        frame = board_frame(camera, np.eye(4), texture, rng)
        t = time.perf_counter()
        rep = check.measure(frame)  # type: ignore[arg-type]
        ms.append((time.perf_counter() - t) * 1e3)
        false_alarms += check.moved(rep)
        worst = (
            max(worst[0], rep.translation_mm),
            max(worst[1], rep.rotation_deg),
            max(worst[2], float(np.nanmax(rep.pixel_shift_px))),
        )
    caught = {"2 mm": 0, "0.2 deg": 0}
    least = {"2 mm": np.inf, "0.2 deg": np.inf}
    for k in range(trials):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        kind = "2 mm" if k % 2 == 0 else "0.2 deg"
        bump = (
            make_pose(translation=0.002 * axis)
            if kind == "2 mm"
            else make_pose(rotation_from_rotvec(np.radians(0.2) * axis))
        )
        frame = board_frame(camera, bump, texture, rng)
        try:
            check.check(frame)  # type: ignore[arg-type]
        except CameraMoved as exc:
            caught[kind] += 1
            least[kind] = min(least[kind], float(np.nanmax(exc.report.pixel_shift_px)))
    n2 = (trials + 1) // 2
    print(
        f"drift: unmoved {false_alarms} false alarms in {still} frames (largest {worst[0]:.2f} mm, {worst[1]:.3f} deg, "
        f"{worst[2]:.3f} px); moved 2 mm caught {caught['2 mm']}/{n2}, 0.2 deg caught "
        f"{caught['0.2 deg']}/{trials - n2} "
        f"(smallest shift of a caught bump {min(least.values()):.2f} px); check median {np.median(ms):.1f} ms at "
        f"640x480, 9 points; {time.perf_counter() - t0:.0f} s; load {load()}"
    )


def emulator_trials(b: Bench, n: int) -> None:
    from normpos_grasp.errors import ZoneIntrusion
    from normpos_grasp.execution import DriverOptions, RtdeDriver, SafetyLimits
    from normpos_grasp.sim.ur_emulator import EmulatorProcess
    from normpos_grasp.watch.monitor import ZoneWatch
    from normpos_grasp.watch.synthetic import ThreadedStream

    host = "127.0.0.83"
    lat, stops, bad, parts = [], [], 0, []
    # the stream renders in this process (a real camera's frames come from its driver's own thread): its fast sensor
    # model (noise, quantisation, dropout; no stereo shadows or edge holes) keeps the renderer's share of the GIL and
    # of the two cores small; section 1 measures detection with the full model
    scene = SyntheticCellStream(b.camera, b.background, b.arm, b.cell.tool, b.sensor, 11, fast=True)
    home = np.asarray(b.cell.home_q, dtype=np.float64)
    with EmulatorProcess(host, "ur5e", ready_timeout_s=60.0) as emu:
        emu.emu("unlock_delay", "0.2")
        driver = RtdeDriver(host, SafetyLimits.for_model("ur5e"), options=DriverOptions(stale_state_s=1.0))
        driver.connect()
        try:
            for k in range(n):
                det = b.detector()
                hand = hand_box(
                    np.array([b.rng.uniform(0.36, 0.64), b.rng.uniform(-0.12, -0.06), b.rng.uniform(0.05, 0.2)])
                )
                appear = float(b.rng.uniform(0.4, 1.2))
                stream = ThreadedStream(
                    scene, lambda: driver.state().q, lambda t, h=hand, a=appear: [h] if t >= a else []
                )
                watch = ZoneWatch(det, stream, driver, q_source=lambda: driver.state().q, max_gap_s=5.0)
                target = home + np.array([0.6, 0.15, -0.2, 0.0, 0.0, 0.4])
                stream.start()
                detail: dict[str, float] = {}
                try:
                    with watch:
                        driver.move_joints([target], 0.4, 1.0)
                    bad += 1  # the move ended without a stop
                except ZoneIntrusion as exc:
                    detail = exc.detail
                stream.close()
                if stream.first_seen:
                    shown = min(stream.first_seen.values())
                    reply = emu.emu("since", f"{shown:.6f}")
                    info = dict(part.split("=", 1) for part in reply.split()[2:] if "=" in part)
                    if info.get("stop") == "stopJ":
                        lat.append((float(info["stop_t"]) - shown) * 1e3)
                        stops.append(int(info["motion_after_stop"]))
                        if "frame_stamp" in detail:
                            # first frame showing it -> frame that tripped -> stop requested -> stopJ sent -> arrived
                            marks = [shown, detail["frame_stamp"], detail["requested_at"], detail["stop_sent_at"]]
                            parts.append(np.diff([*marks, float(info["stop_t"])]) * 1e3)
                driver.resume()
                driver.move_joints([home], 1.0, 2.0)
                _ = k
        finally:
            driver.disconnect()
    arr = np.array(lat) if lat else np.array([np.nan])
    print(
        f"loopback controller (real ur_rtde client, moveJ at 0.4 rad/s): {len(lat)}/{n} stopped by stopJ; stop arrival "
        f"after the first frame showing the hand: median {np.median(arr):.0f} ms, max {arr.max():.0f} ms; motion "
        f"commands after the stop {sum(stops)}; moves not stopped {bad}; load {load()}"
    )
    if parts:
        med = np.median(np.array(parts), axis=0)
        print(
            f"  where the time goes (medians, ms): first frame showing it -> frame that tripped {med[0]:.0f}; -> stop "
            f"requested (waiting for the watch thread, the check) {med[1]:.0f}; -> stopJ sent (driver's next poll) "
            f"{med[2]:.0f}; -> arrived at the controller {med[3]:.0f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--cycles", type=int, default=1000)
    ap.add_argument("--frames-per-cycle", type=int, default=6)
    ap.add_argument("--emulator", type=int, default=10)
    ap.add_argument("--drift-trials", type=int, default=100)
    ap.add_argument("--still-frames", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(f"load average before: {load()}")
    b = Bench(args.seed)
    if args.trials:
        intrusion_trials(b, args.trials)
    if args.cycles:
        false_stop_cycles(b, args.cycles, args.frames_per_cycle)
    if args.emulator:
        emulator_trials(b, args.emulator)
    if args.drift_trials or args.still_frames:
        drift_trials(b, args.drift_trials, args.still_frames)


if __name__ == "__main__":
    main()
