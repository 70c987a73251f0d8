"""Loopback addresses for the tests' emulators, one per test process.

An emulated controller binds its RTDE, dashboard and script ports on one 127.x.y.z address. A fixed address collides
when two test runs share a machine (two checkouts, a developer's run beside CI's): the second emulator cannot bind
and its test fails. The second and third octets come from the process id (as tests/test_execution_faults.py's
HOST), the last from the test, so tests of one process differ by `last` and processes differ by pid.
"""

from __future__ import annotations

import os


def loopback_host(last: int) -> str:
    """127.<100 + pid % 100>.<pid // 100 % 250 + 1>.<last> for this process (last: 1-254, unique per test file)."""
    if not 1 <= last <= 254:
        raise ValueError(f"last octet must be 1-254, got {last}")
    pid = os.getpid()
    return f"127.{100 + pid % 100}.{pid // 100 % 250 + 1}.{last}"
