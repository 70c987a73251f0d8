"""Replay bundles: one cycle of the cell loop kept on disk (frame, camera, masks, fits, plan, execution, cell,
options, twin) and re-run offline to show what differs. `bundle` writes and reads them, `replay` compares."""

from normpos_grasp.replay.bundle import BUNDLE_FORMAT, Bundle, BundleRecorder, load_bundle, write_bundle
from normpos_grasp.replay.replay import ReplayMismatch, ReplayReport, assert_replays, replay_bundle

__all__ = [
    "BUNDLE_FORMAT",
    "Bundle",
    "BundleRecorder",
    "ReplayMismatch",
    "ReplayReport",
    "assert_replays",
    "load_bundle",
    "replay_bundle",
    "write_bundle",
]
