"""Trajectories (paper §II-A, II-B, II-D): quintic B-splines, the robot's limits, the NSGA-II planner,
the validator every plan passes before it moves an arm, and task programs."""
