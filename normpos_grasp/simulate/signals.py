"""Signals of long runs (`simulate`, `synth`): the names these commands use, from the one signal helper of the
package (`normpos_grasp.interrupts`, standard library only, so a spawned worker still imports it within
milliseconds and arms the parent-death signal before the pipeline is imported)."""

from __future__ import annotations

from normpos_grasp.interrupts import Interrupted, init_worker, signals_deferred, signals_ignored, signals_raise

__all__ = ["Interrupted", "init_worker", "signals_deferred", "signals_ignored", "signals_raise"]
