"""Watching the cell while the arm moves: zone intrusions stop the arm, a moved camera stops the loop.

An extra layer for the integrator, NOT a replacement for the robot's rated safety functions (protective stops,
safety-rated speed and separation monitoring, light curtains, scanners). docs/watch.md.

zones: watched volumes of the cell YAML; expected: the depth the camera should see (last measurement, the arm's
predicted silhouette at the commanded joints, the held part); intrusion: the per-frame detector; person: a shape rule
naming person-sized intruders; monitor: the thread that runs the detector on a depth stream and stops the arm;
drift: the static-reference check in every frame; synthetic: a cheap synthetic depth stream (arm, intruders, sensor
noise) for tests, benchmarks and the simulated cell.
"""
