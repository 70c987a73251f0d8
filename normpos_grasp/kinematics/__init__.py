"""Robot kinematics for UR arms: parameter table, FK/Jacobians (pinocchio), analytic and differential IK."""
