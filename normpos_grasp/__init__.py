"""normpos-grasp: norm-position measurement, CAD template fitting and grasp planning for UR pick-and-place cells.

The pipeline: RGB-D frame -> instance segmentation -> norm-position of every object -> template pose fit ->
collision world -> grasp candidates per object shape -> IK/reachability/collision checks -> pick-and-place
plan -> UR arm over RTDE or simulation. SI units everywhere; poses are 4x4 `a_from_b` matrices.
"""

__version__ = "0.1.0"
