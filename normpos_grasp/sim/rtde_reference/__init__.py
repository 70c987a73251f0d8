"""An independent loopback UR controller (RTDE, dashboard, script ports) for ur_rtde clients.

Written from the protocol notes (shared/reference/rtde_notes.md) without the code of
`normpos_grasp.sim.ur_emulator`, so that the fault campaign checks the driver against two implementations of UR's
controller protocol instead of one that may share the driver author's assumptions. `ReferenceControllerProcess`
runs it as its own process (ur_rtde's constructors hold the GIL while they wait for data, so a server in the
client's interpreter would deadlock).
"""

from .controller import ReferenceController, Settings
from .process import ReferenceControllerProcess

__all__ = ["ReferenceController", "ReferenceControllerProcess", "Settings"]
