"""Overlapped cycles (run_cell_loop(overlap=True)): the next frame is perceived and planned while the arm places."""

from __future__ import annotations

import numpy as np
import pytest

from normpos_grasp.cell import resolve_cell
from normpos_grasp.errors import DriverFault, ZoneIntrusion
from normpos_grasp.execution import DriverOptions, SafetyLimits, SimDriver
from normpos_grasp.loop import PickRecord, SyntheticBinSource, run_cell_loop
from normpos_grasp.records.instance import Instance
from normpos_grasp.sim.parts import default_part_library

CELL = resolve_cell("ur5e_bin_parallel")
HOME = np.asarray(CELL.home_q, dtype=np.float64)
LIBRARY = default_part_library()


def _driver(time_scale: float = 6.0) -> SimDriver:
    # 6x simulated time keeps the test short; the watchdog is relaxed for a loaded 2-core machine
    driver = SimDriver(
        SafetyLimits.from_cell(CELL),
        q_home=HOME,
        time_scale=time_scale,
        options=DriverOptions(stale_state_s=1.0, watchdog_s=1.0),
    )
    driver.connect()
    return driver


def _picks(records: list[PickRecord]) -> list[tuple[str, str, str]]:
    out = []
    for r in records:
        plan = r.result.plan
        chosen = plan.chosen.candidate if plan is not None and plan.chosen is not None else None
        out.append((r.status, chosen.template if chosen else "", chosen.grasp_id if chosen else ""))
    return out


def _run(overlap: bool) -> tuple[list[PickRecord], list[str]]:
    source = SyntheticBinSource(CELL, count=2, seed=2, validate_physics=False, library=LIBRARY)
    events: list[str] = []
    capture, check = source.capture, source.check_pick
    source.capture = lambda: events.append("capture") or capture()  # type: ignore[method-assign]
    source.check_pick = lambda plan: events.append("check") or check(plan)  # type: ignore[method-assign]
    driver = _driver()
    try:
        records = run_cell_loop(
            CELL, source, source.ground_truth_segmenter(), LIBRARY, driver, execute=True, max_picks=2,
            overlap=overlap,
        )  # fmt: skip
    finally:
        driver.disconnect()
        driver.shutdown()
    return records, events


def test_overlapped_loop_picks_what_the_sequential_loop_picks() -> None:
    sequential, seq_events = _run(False)
    overlapped, ovl_events = _run(True)
    assert _picks(overlapped) == _picks(sequential), (_picks(sequential), _picks(overlapped))
    assert [s for s, _, _ in _picks(sequential)] == ["picked"] * 2
    assert ovl_events == seq_events  # the source sees the same captures and checks, in the same order
    for r in overlapped[1:]:  # every later turn was prepared during the previous place, from its last waypoint
        assert "overlap_wait" in r.timings_ms
        assert r.start_q is not None and r.plan_json is not None
        assert np.allclose(r.start_q, r.plan_json["joint_waypoints"][0]["q"])
    assert "overlap_wait" not in overlapped[0].timings_ms


class _FailsSecondFrame:
    """The ground truth for the first frame, then an error (a perception bug in the worker)."""

    def __init__(self, source: SyntheticBinSource) -> None:
        self.truth = source.ground_truth_segmenter()
        self.calls = 0

    def segment(self, frame: object) -> list[Instance]:
        self.calls += 1
        if self.calls > 1:
            raise RuntimeError("segmenter failed on the overlapped frame")
        return self.truth.segment(frame)  # type: ignore[arg-type]


def test_worker_exception_stops_the_arm_during_the_place_and_ends_the_loop() -> None:
    source = SyntheticBinSource(CELL, count=2, seed=2, validate_physics=False, library=LIBRARY)
    segmenter = _FailsSecondFrame(source)
    driver = _driver(time_scale=1.0)  # real time: the place (about 2 s after the retreat) outlasts the worker's failure
    heard: list[PickRecord] = []
    try:
        with pytest.raises(RuntimeError, match="overlapped frame") as caught:
            run_cell_loop(
                CELL, source, segmenter, LIBRARY, driver, execute=True, max_picks=2, overlap=True,
                on_pick=heard.append,
            )  # fmt: skip
        assert isinstance(caught.value.__cause__, ZoneIntrusion)  # the arm was stopped by the driver's stop path
        state = driver.state()
        assert np.max(np.abs(state.qd)) < 1e-6  # at rest
        fault = driver.fault
        assert fault is not None  # latched: nothing further is sent until resume()
        with pytest.raises(DriverFault, match="halted by ZoneIntrusion"):
            driver.move_joints(HOME[None], 0.5, 0.5)
    finally:
        driver.disconnect()
        driver.shutdown()
    assert heard == [] and segmenter.calls == 2  # no turn was recorded as done and nothing planned after the error
