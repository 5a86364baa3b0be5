"""The cell's geometry for speed and separation monitoring (issue 52): the person's distance to the arm and
its tool, against a brute-force reference; a range read on the safe side; the tool's points in the top
speed; ISO 13855's C, and the settings that refuse a smaller one or a cell with no source."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import msgspec
import numpy as np
import pytest

from common.robot.ur16e import N_JOINTS
from common.runtime.errors import ConfigError
from common.safety.geometry import (
    LINK_RADII_M,
    Arm,
    Body,
    Pose,
    Sensor,
    Tool,
    intrusion_iso13855,
    separation,
)
from services.executor.settings import Settings, SourceSettings

RNG_SEED = 52
TOOL = Tool.of([[0.0, 0.0, 0.15, 0.12], [0.1, 0.0, 0.2, 0.05]])


def brute_distance(body: Body, p: np.ndarray, n: int = 2001) -> float:
    """The least distance from ``p`` to the body, each capsule's axis sampled every ~0.5 mm."""
    u = np.linspace(0.0, 1.0, n)[:, None]
    best = math.inf
    for a, b, r in zip(body.a, body.b, body.r, strict=True):
        axis = a + u * (b - a)
        best = min(best, float(np.linalg.norm(axis - p, axis=1).min()) - r)
    return max(0.0, best)


def test_the_distance_to_arm_and_tool_is_the_brute_force_one_at_random_poses_and_places() -> None:
    rng = np.random.default_rng(RNG_SEED)
    print(f"seed {RNG_SEED}")
    for _ in range(40):
        q = rng.uniform(-math.pi, math.pi, N_JOINTS)
        arm = Arm(Pose(*rng.uniform(-2, 2, 3), rng.uniform(-180, 180)), TOOL)
        body = arm.body(q)
        centre = arm.base.place(np.zeros((1, 3)))[0]
        points = centre + rng.normal(0.0, 1.0, (5, 3))
        expected = min(brute_distance(body, p) for p in points)
        assert body.distance(points) == pytest.approx(expected, abs=1e-3)


def test_the_tool_is_part_of_the_body_and_the_base_pose_moves_it() -> None:
    q = np.zeros(N_JOINTS)
    bare, tooled = Arm().body(q), Arm(tool=TOOL).body(q)
    assert len(tooled.r) == len(bare.r) + 2
    moved = Arm(Pose(5.0, 0.0, 0.0, 90.0)).body(q)
    # the stretched arm points along -x of its base; turned 90°, along -y, 5 m away
    assert moved.a[0] == pytest.approx([5.0, 0.0, 0.0])
    assert moved.b[-1][1] < -0.8 and moved.b[-1][0] == pytest.approx(5.0 + 0.2907, abs=1e-3)


def test_a_range_is_read_on_the_safe_side_wherever_the_person_stands_at_that_range() -> None:
    """A plain range says the person is that far from the sensor, in no direction: S is never more than
    the distance of any point at that range (sampled on the sphere), for sensors anywhere in the cell."""
    rng = np.random.default_rng(RNG_SEED + 1)
    arm = Arm(tool=TOOL)
    for _ in range(30):
        body = arm.body(rng.uniform(-math.pi, math.pi, N_JOINTS))
        sensor = Sensor("s", Pose(*rng.uniform(-3, 3, 2), 0.0, rng.uniform(-180, 180)), 0.85)
        d = rng.uniform(0.0, 6.0)
        s = separation(body, sensor, d, None, to_robot=False, placed=False)
        directions = rng.normal(size=(2000, 3))
        sphere = (
            sensor.pose.place(np.zeros((1, 3)))[0]
            + d * directions / np.linalg.norm(directions, axis=1)[:, None]
        )
        assert s <= min(body.distance(p[None]) for p in sphere[:200]) + 1e-9
        assert s <= body.distance(sphere) + 1e-9


def test_a_scanner_at_the_base_takes_the_arms_extent_off_its_range_and_to_robot_takes_it_as_it_is() -> None:
    body = Arm(tool=TOOL).body(np.zeros(N_JOINTS))
    at_base = Sensor("scanner", Pose(), 1.2)
    reach = body.reach(np.zeros(3))
    assert 1.0 < reach < 1.3  # the UR16e stretched (0.9 m and its links' radii) and its tool
    assert separation(body, at_base, 2.0, None, False, False) == pytest.approx(2.0 - reach)
    assert separation(body, at_base, 0.6, None, False, False) == 0.0
    assert separation(body, at_base, 2.0, None, True, False) == 2.0
    assert separation(body, Sensor("t", Pose(), 0.85, to_robot=True), 2.0, None, False, False) == 2.0


def test_points_are_placed_by_the_sensors_pose_unless_already_placed() -> None:
    body = Arm().body(np.zeros(N_JOINTS))
    sensor = Sensor("cam", Pose(3.0, 0.0, 0.0, 180.0), 0.85)
    seen = np.array([[1.5, 0.0, 0.5]])  # 1.5 m in front of a camera at x = 3 facing the base: x = 1.5
    assert separation(body, sensor, 1.5, seen, False, False) == pytest.approx(
        body.distance(np.array([[1.5, 0, 0.5]]))
    )
    assert separation(body, sensor, 1.5, seen, False, True) == pytest.approx(body.distance(seen))
    assert np.allclose(sensor.pose.local(sensor.pose.place(seen)), seen)


def test_a_wrist_3_spin_moves_the_tool_and_a_wrist_1_turn_moves_its_tip_faster_than_the_flange() -> None:
    """Issue 52's figures: a wrist-3 spin read 0 m/s at the flange, a gripper tip 0.1 m off its axis
    moves at ω r; a wrist-1 turn moves a 0.2 m tool's tip faster than the flange."""
    from tests.support.arm import OMEGA, wrist_speeds

    s = wrist_speeds()
    assert s["spin_flange"] == pytest.approx(OMEGA * LINK_RADII_M[5], rel=1e-3)  # the wrist's housing rim
    assert s["spin_tip"] == pytest.approx(OMEGA * 0.1, rel=1e-3)
    flange, tool = s["turn_flange"], s["turn_tip"]
    print(f"wrist 1 at 180°/s: bare arm {flange:.2f} m/s, tip of a 0.2 m tool {tool:.2f} m/s")
    assert (round(flange, 2), round(tool, 2)) == (0.79, 1.06)
    assert len(LINK_RADII_M) == 6


def surface_samples(arm: Arm, q: np.ndarray, n: int) -> list[tuple[int, np.ndarray]]:
    """Material points on every capsule's and sphere's surface, each as (its link's frame index, its
    coordinates in that frame): a Fibonacci sphere of ``n`` directions about each capsule's ends and
    sphere's centre, and rings along each capsule's length."""
    from common.robot.ur16e import frames

    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * k
    dirs = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], axis=1)
    f = frames(q)[0]
    origins = np.vstack([np.zeros(3), f[:, :3, 3]])
    out = []
    for i, r in enumerate(LINK_RADII_M):  # capsule i rides link i + 1 (DH frame i)
        ends = origins[i] + np.linspace(0.0, 1.0, 9)[:, None] * (origins[i + 1] - origins[i])
        cell = (ends[:, None, :] + r * dirs[None]).reshape(-1, 3)
        out.append((i, (cell - f[i, :3, 3]) @ f[i, :3, :3]))
    for c in arm.tool.spheres:
        out.append((5, c[:3] + c[3] * dirs))
    return out


def test_the_fastest_point_of_arm_and_tool_is_a_dense_samples_top_never_less() -> None:
    """Issue 74: v_r is the fastest point of the real arm (capsules that enclose its housings) and tool.
    Over random states, material points sampled densely on every surface, moved with their links for a
    microsecond, are never faster than the reported v_r, and the fastest of them is within 1 % of it."""
    from common.robot.ur16e import UR16E, frames

    rng = np.random.default_rng(RNG_SEED)
    arm, h = Arm(tool=TOOL), 1e-6
    ratios = []
    for _ in range(40):
        q = rng.uniform(-math.pi, math.pi, N_JOINTS)
        qd = rng.uniform(-1.0, 1.0, N_JOINTS) * UR16E.velocity
        reported = float(arm.speeds(q[None], qd[None])[0])
        f0, f1 = frames(q)[0], frames(q + qd * h)[0]
        top = 0.0
        for link, local in surface_samples(arm, q, 2000):
            p0 = local @ f0[link, :3, :3].T + f0[link, :3, 3]
            p1 = local @ f1[link, :3, :3].T + f1[link, :3, 3]
            top = max(top, float(np.linalg.norm(p1 - p0, axis=1).max() / h))
        ratios.append(top / reported)
    print(f"dense sample / reported v_r over 40 states: {min(ratios):.4f}–{max(ratios):.4f}")
    assert max(ratios) <= 1.0 + 1e-5  # never above (a finite difference of a microsecond)
    assert min(ratios) >= 0.99


@pytest.mark.parametrize(
    ("detects", "resolution", "height", "c"),
    [
        ("legs", None, 0.0, 1.2),  # a scanner's plane at the floor: 1200 mm
        ("legs", None, 0.3, 1.08),  # 1200 − 0.4·300
        ("legs", None, 0.875, 0.85),  # 850 mm from H = 875 mm up
        ("legs", 70, 0.3, 1.08),  # 15 (d − 50) = 300 mm: just high enough for an ankle
        ("body", None, 0.0, 0.85),
        ("arm", 55, 0.0, 0.85),
        ("hand", 14, 0.0, 0.0),  # 8 (d − 14)
        ("hand", 30, 0.0, 0.128),
        ("hand", 40, 0.0, 0.208),
    ],
)
def test_iso_13855_intrusion_distances(
    detects: str, resolution: float | None, height: float, c: float
) -> None:
    assert intrusion_iso13855(detects, resolution, height) == pytest.approx(c)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("source", "says"),
    [
        ({"name": "scanner:front", "detects": "legs", "height_m": 0.3, "intrusion_m": 0.2},
         "'scanner:front': intrusion_m = 0.2 m is below ISO 13855's C = 1.080 m"),
        ({"name": "cam", "detects": "hand", "resolution_mm": 60}, "'cam': a sensor that detects hands"),
        ({"name": "low", "detects": "legs", "resolution_mm": 90, "height_m": 0.2},
         "needs the plane at 0.60 m"),
        ({"name": "high", "detects": "legs", "height_m": 1.4}, "does not see legs"),
    ],
)  # fmt: skip
def test_a_source_whose_c_is_below_iso_13855s_is_refused_naming_it(source: dict, says: str) -> None:
    s = msgspec.convert({"separation": True, "separation_sources": [source]}, Settings)
    with pytest.raises(ConfigError, match=r"\[executor\] separation_sources") as e:
        s.sensors()
    assert says in str(e.value)
    assert "\n" not in str(e.value)


def test_a_bare_name_is_a_scanner_at_the_base_seeing_legs_at_the_floor_and_a_larger_c_is_kept() -> None:
    s = msgspec.convert(
        {"separation": True, "separation_sources": ["scanner:front", {"name": "cam", "detects": "body",
                                                                     "intrusion_m": 1.0}]},
        Settings,
    )  # fmt: skip
    sensors = s.sensors()
    assert sensors["scanner:front"] == Sensor("scanner:front", Pose(), 1.2, False)
    assert sensors["cam"].intrusion_m == 1.0
    assert SourceSettings.parse("scanner:front:1.5,0,180:legs@0.3") == SourceSettings(
        "scanner:front", (1.5, 0.0, 0.0, 180.0), "legs", height_m=0.3
    )
    with pytest.raises(ValueError, match="NAME:X,Y,YAW:KIND"):
        SourceSettings.parse("scanner")


def test_a_ceiling_camera_looking_down_is_placed_by_its_pitch_and_a_single_beam_has_c_1200_mm() -> None:
    """A full pose (issue 74: poses were yaw only, so a camera on the ceiling could not be placed): at 3 m,
    pitched 90°, its x axis points at the floor, and a point 2 m along it stands 1 m above the floor."""
    cam = SourceSettings.parse("cam:top:1,0,3,0,90,0:hand,resolution=14").sensor()
    assert np.allclose(cam.pose.place(np.array([[2.0, 0.0, 0.0]])), [[1.0, 0.0, 1.0]])
    assert cam.intrusion_m == 0.0
    rolled = SourceSettings.parse("cam:side:0,0,1,90,0,0:body").sensor()  # rolled: its y axis points up
    assert np.allclose(rolled.pose.place(np.array([[0.0, 1.0, 0.0]])), [[0.0, 0.0, 2.0]])
    assert np.allclose(cam.pose.local(cam.pose.place(np.array([[0.3, -0.2, 0.5]]))), [[0.3, -0.2, 0.5]])
    assert SourceSettings.parse("beam:door:2,0,90:beam").sensor().intrusion_m == pytest.approx(1.2)


@pytest.mark.parametrize(
    ("scanner", "says"),
    [
        ("cam:0,0,3,0,90,0:hand", "a sensor that detects hands needs a resolution"),  # which it cannot say
        ("front:1,0,0:legs@1.5", "does not see legs"),
        ("front:1,0,0.3,0:legs,height=0.5", "height_m = 0.5 m, but its pose stands at z = 0.3 m"),
        ("front:1,0,0:legs,c=0.9", "below ISO 13855's C = 1.200 m"),
        ("front:1,0,0:legs,range=3", "unknown option 'range=3'"),
        ("front:1,0:legs", "a pose is X,Y,YAW"),
    ],
)
def test_install_refuses_a_scanner_the_executor_would_refuse_in_one_line(scanner: str, says: str) -> None:
    with pytest.raises(ValueError) as e:
        SourceSettings.parse(scanner)
    assert says in str(e.value) and "\n" not in str(e.value)


def test_monitoring_on_with_no_declared_source_is_refused_at_start_in_one_line() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "services.executor"],
        env={**os.environ, "CADENCE_EXECUTOR_SEPARATION": "true"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1, r.stderr
    assert "separation = true needs separation_sources" in r.stderr
