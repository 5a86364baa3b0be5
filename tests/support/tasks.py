"""Small task programs: ``GOOD`` loads (the tests of bad task files change one thing of it); ``TINY``
a pareto store plans in a second (a small population, few generations)."""

from __future__ import annotations

GOOD = """
[task]
name = "t"

[[paths]]
id = "p1"
unit = "deg"
waypoints = [[0, -90, 90, -90, -90, 0], [30, -80, 100, -100, -90, 20], [45, -70, 95, -110, -90, 40]]

[[paths]]
id = "p2"
unit = "rad"
waypoints = [[0.785, -1.22, 1.66, -1.92, -1.571, 0.698], [0, -1.571, 1.571, -1.571, -1.571, 0]]
"""

TINY = """
[task]
name = "tiny"
[planner]
population = 16
generations = 6
n_solutions = 5
[[paths]]
id = "a"
unit = "deg"
waypoints = [[0, -90, 90, -90, -90, 0], [30, -80, 100, -100, -90, 20], [45, -70, 95, -110, -90, 40]]
[[paths]]
id = "b"
unit = "deg"
waypoints = [[45, -70, 95, -110, -90, 40], [0, -90, 90, -90, -90, 0]]
"""
