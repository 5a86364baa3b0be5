"""The cell's geometry for speed and separation monitoring (DESIGN §8; ISO/TS 15066 §5.5.4, ISO 13855): where
the robot, its tool and each sensor stand, how far a person is from the arm and its tool, how fast the
fastest point of arm and tool moves, and each sensor's intrusion distance C.

Frames. The cell frame is the floor's: z up, its origin where the integrator puts it (by default at the
robot's base). The robot's base and each sensor are placed in it by a ``Pose`` (x, y, z in metres, a yaw
about z in degrees: robots and scanners stand on the floor or hang from a ceiling beam facing down,
and a yaw is what an integrator measures). The tool is given in the flange frame (DH frame 6).

The arm as a person can meet it. The DH origins of the UR16e do not lie on its links: the upper arm
runs beside the shoulder-elbow line by the shoulder offset (about 0.176 m) and the forearm by what the
elbow offset (about 0.137 m) leaves. Each link is therefore a capsule around the segment between two DH
origins, with a radius that encloses the real link: the offset plus the tube's radius
(``LINK_RADII_M``). The tool and its payload are spheres in the flange frame. The distance from a
person's point to the arm is its least distance to any capsule or sphere surface (0 inside).

The arm's speed is the top speed of any point of the same capsules and spheres, exactly. A capsule rides
one link (the segment from DH origin i to i+1 lies on link i+1: origin i is on joint i+1's axis), so a
point p of it moves at v(p) = v_a + ω × (p − a). Over a ball of radius r about a centre moving at v, the
fastest point moves at √(|v∥|² + (|v⊥| + |ω| r)²) (v split along ω and across it: ω × r n sweeps a disc
across ω); that is convex in v, and along the segment v is affine, so the fastest point of a capsule lies
on one of its end caps. A wrist-3 spin therefore moves a gripper's tip though the flange's centre stays
put, and a housing's rim moves faster than the DH line it surrounds (issue 74: over random states the
fastest surface point was up to 1.86× the DH origins' top speed).

The radii (``LINK_RADII_M``) enclose the UR16e's housings: its joints are drums of about 0.09 m radius,
whose rims at the shoulder and the elbow stood 17 mm outside a 0.25 m upper-arm capsule and at the wrists
10 mm outside 0.075 m ones (issue 74's review, from UR's published dimensions); each radius here is the
rim's distance rounded up to 5 mm.

What a reading says (``Reading``): the person's nearest points in the sensor's frame (placed by its
pose), a distance the sensor measured to the robot already, or a plain range from the sensor (the
nearest object is that far from the sensor, in a direction it does not say). A range is read on the safe
side: the person may stand anywhere at that distance from the sensor, so the nearest they can be to the
arm is the range less the farthest the arm reaches from the sensor (``reach``), never less than 0. A
scanner at the robot's base that says 2 m therefore means 2 m less the arm's extent, not 2 m.

C (ISO 13855 §6, the table in DESIGN §8):
- hand (a resolution d ≤ 40 mm, a light curtain or a 3D sensor that sees fingers): C = 8 (d − 14) mm, ≥ 0;
- arm (40 < d ≤ 70 mm): C = 850 mm, the reach of an arm past the field;
- body (d > 70 mm, a multi-beam curtain or a sensor that sees the trunk): C = 850 mm;
- legs (a scanner's plane parallel to the floor at height H): C = 1200 − 0.4 H mm, at least 850 mm
  (H at most 1000 mm, and at least 15 (d − 50) mm for its resolution to see an ankle);
- beam (a single beam, ISO 13855 §6.3's single-beam case): C = 1200 mm.
A declared C below that is refused: a smaller C is a person's arm reaching past the sensor unseen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from common.robot.stopping import NO_STOPS, RobotStops
from common.robot.ur16e import frames

Array = NDArray[np.float64]
Detects = Literal["hand", "arm", "body", "legs", "beam"]

# the capsule around each segment between DH origins: base → shoulder (the column), shoulder → elbow (the
# upper arm, offset by the shoulder offset), elbow → wrist 1 (the forearm), then the wrists
LINK_RADII_M = np.array([0.09, 0.27, 0.10, 0.085, 0.085, 0.085])


def intrusion_iso13855(detects: Detects, resolution_mm: float | None = None, height_m: float = 0.0) -> float:
    """C in metres for a sensor that detects ``detects`` (module docstring); ``resolution_mm`` d where the
    sensor has one (hands: required), ``height_m`` the plane's height above the floor (legs)."""
    if detects == "hand":
        if resolution_mm is None or resolution_mm > 40.0:
            raise ValueError("a sensor that detects hands needs a resolution of at most 40 mm")
        return max(0.0, 8.0 * (resolution_mm - 14.0)) / 1000.0
    if detects in ("arm", "body"):
        return 0.85
    if detects == "beam":  # a single beam: a person may reach over or under it
        return 1.2
    if height_m > 1.0:
        raise ValueError(f"a scanner's plane at {height_m:g} m does not see legs (ISO 13855: H ≤ 1.0 m)")
    if resolution_mm is not None and height_m * 1000.0 < 15.0 * (resolution_mm - 50.0):
        low = 15.0 * (resolution_mm - 50.0) / 1000.0
        raise ValueError(f"a resolution of {resolution_mm:g} mm needs the plane at {low:.2f} m or higher")
    return max(0.85, 1.2 - 0.4 * height_m)


@dataclass(frozen=True, slots=True)
class Pose:
    """A placement in the cell frame: a translation (m) and a yaw about z (degrees); for a sensor that does
    not stand level (a camera on a ceiling looking down), a pitch and a roll too: the rotation is
    Rz(yaw) Ry(pitch) Rx(roll), so a pitch of 90° turns the sensor's x axis straight down."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0

    def matrix(self) -> Array:
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        m = np.array([[c, -s, 0, self.x], [s, c, 0, self.y], [0, 0, 1, self.z], [0, 0, 0, 1.0]])
        if self.pitch_deg or self.roll_deg:
            cp, sp = math.cos(math.radians(self.pitch_deg)), math.sin(math.radians(self.pitch_deg))
            cr, sr = math.cos(math.radians(self.roll_deg)), math.sin(math.radians(self.roll_deg))
            tilt = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ np.array(
                [[1, 0, 0], [0, cr, -sr], [0, sr, cr]]
            )
            m[:3, :3] = m[:3, :3] @ tilt
        return m

    def place(self, points: Array) -> Array:
        """Points (n, 3) given in this pose's frame, in the frame it is placed in."""
        m = self.matrix()
        return np.asarray(points, dtype=float) @ m[:3, :3].T + m[:3, 3]

    def local(self, points: Array) -> Array:
        """Points (n, 3) in the frame this pose is placed in, in this pose's own frame."""
        m = self.matrix()
        return (np.asarray(points, dtype=float) - m[:3, 3]) @ m[:3, :3]


@dataclass(frozen=True, slots=True)
class Tool:
    """Tool and payload as spheres in the flange frame: rows (x, y, z, r), metres. The TCP is the first
    sphere's centre by convention (a gripper's fingers), the others its body and what it carries."""

    spheres: Array

    @classmethod
    def of(cls, rows: list[list[float]] | Array) -> Tool:
        a = np.asarray(rows, dtype=float).reshape(-1, 4)
        if np.any(a[:, 3] < 0.0) or not np.all(np.isfinite(a)):
            raise ValueError("a tool sphere is x, y, z, r with r ≥ 0 (metres, flange frame)")
        return cls(a)


NO_TOOL = Tool(np.zeros((0, 4)))


@dataclass(frozen=True, slots=True)
class Body:
    """The arm and its tool at one pose, in the cell frame: capsules (a, b, r) and spheres (c, r)."""

    a: Array  # (S, 3)
    b: Array  # (S, 3)
    r: Array  # (S,)

    def distance(self, points: Array) -> float:
        """The least distance from any of ``points`` (n, 3) to the body's surface (0 inside)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        if not len(p):
            return math.inf
        ab = self.b - self.a  # (S, 3)
        ap = p[:, None, :] - self.a[None, :, :]  # (n, S, 3)
        length2 = np.einsum("ij,ij->i", ab, ab)
        u = np.einsum("nsj,sj->ns", ap, ab) / np.where(length2 > 0, length2, 1.0)
        u = np.clip(np.where(length2 > 0, u, 0.0), 0.0, 1.0)
        nearest = self.a[None] + u[..., None] * ab[None]
        d = np.linalg.norm(p[:, None, :] - nearest, axis=2) - self.r[None, :]
        return max(0.0, float(d.min()))

    def reach(self, origin: Array) -> float:
        """The farthest any point of the body lies from ``origin`` (3,)."""
        o = np.asarray(origin, dtype=float)
        far = np.maximum(np.linalg.norm(self.a - o, axis=1), np.linalg.norm(self.b - o, axis=1))
        return float((far + self.r).max())


@dataclass(frozen=True, slots=True)
class Arm:
    """The robot in the cell: its base's pose, its tool, and its own stops (common/robot/stopping.py)."""

    base: Pose = Pose()
    tool: Tool = NO_TOOL
    stops: RobotStops = NO_STOPS

    def body(self, q: Array) -> Body:
        """The arm and tool at joints q (6,) as capsules, in the cell frame (a sphere is a capsule of no
        length)."""
        f = frames(q)[0]
        base = self.base.matrix()
        origins = np.vstack([np.zeros(3), f[:, :3, 3]])  # base, then DH origins 1–6
        a, b, r = origins[:-1], origins[1:], LINK_RADII_M
        if len(self.tool.spheres):
            c = self.tool.spheres[:, :3] @ f[5, :3, :3].T + f[5, :3, 3]
            a, b, r = np.vstack([a, c]), np.vstack([b, c]), np.concatenate([r, self.tool.spheres[:, 3]])
        return Body(a @ base[:3, :3].T + base[:3, 3], b @ base[:3, :3].T + base[:3, 3], r)

    def speeds(self, q: Array, qd: Array) -> Array:
        """For joint rows q (m, 6) moving at qd (m, 6): (m,), the speed of the fastest point of arm and
        tool (module docstring; a speed does not depend on where the base stands)."""
        f = frames(q)
        m = len(f)
        origins = np.concatenate([np.zeros((m, 1, 3)), f[:, :, :3, 3]], axis=1)  # base, DH origins 1–6
        axes = np.concatenate([np.broadcast_to([0.0, 0.0, 1.0], (m, 1, 3)), f[:, :5, :3, 2]], axis=1)
        turns = np.asarray(qd, dtype=float)[:, :, None] * axes  # joint j's contribution to ω, (m, 6, 3)
        omega = np.cumsum(turns, axis=1)  # link j+1's angular velocity
        v = np.zeros_like(origins)  # each origin's velocity: the joints before it turning it about theirs
        for i in range(1, 7):
            v[:, i] = np.cross(turns[:, :i], origins[:, i, None] - origins[:, :i]).sum(axis=1)
        w = np.linalg.norm(omega, axis=2)  # (m, 6)
        link = np.maximum(_ball(v[:, :-1], omega, w * LINK_RADII_M), _ball(v[:, 1:], omega, w * LINK_RADII_M))
        top = link.max(axis=1)
        if len(self.tool.spheres):
            r6 = f[:, 5, :3, :3]
            arm = np.einsum("mij,sj->msi", r6, self.tool.spheres[:, :3])  # flange to each centre, cell frame
            w6 = omega[:, 5]
            vc = v[:, 6, None] + np.cross(w6[:, None], arm)
            top = np.maximum(top, _ball(vc, w6[:, None], w[:, 5, None] * self.tool.spheres[:, 3]).max(axis=1))
        out: Array = top
        return out

    def top_speed(self, q: Array, dt: float) -> float:
        """The top speed of any point of arm and tool along joint rows q taken every ``dt`` s (each step's
        joint speeds at its middle)."""
        q = np.asarray(q, dtype=float)
        if len(q) < 2:
            return 0.0
        return float(self.speeds((q[1:] + q[:-1]) / 2, np.diff(q, axis=0) / dt).max())


def _ball(v: Array, omega: Array, spin: Array) -> Array:
    """The speed of the fastest point of balls whose centres move at v (..., 3), turning at omega (..., 3),
    with ``spin`` = |ω| r (...): √(|v∥|² + (|v⊥| + |ω| r)²) (module docstring)."""
    w = np.linalg.norm(omega, axis=-1, keepdims=True)
    axis = np.divide(omega, w, out=np.zeros_like(omega), where=w > 0)
    along = (v * axis).sum(axis=-1)
    across = np.linalg.norm(v - along[..., None] * axis, axis=-1)
    out: Array = np.sqrt(along**2 + (across + spin) ** 2)
    return out


@dataclass(frozen=True, slots=True)
class Sensor:
    """A separation source as the executor knows it: where it stands, its C, and what its plain distances
    mean (``to_robot``: already measured to the arm; else a range from the sensor)."""

    name: str
    pose: Pose
    intrusion_m: float
    to_robot: bool = False


def separation(
    body: Body,
    sensor: Sensor,
    distance_m: float,
    points: Array | None,
    to_robot: bool,
    placed: bool,
) -> float:
    """S, the least distance from the person a reading describes to the arm and tool at ``body`` (module
    docstring): its points (in the sensor's frame, or the cell's when ``placed``), a distance to the
    robot, or a range from the sensor read on the safe side."""
    if points is not None and len(points):
        cell = points if placed else sensor.pose.place(points)
        return body.distance(cell)
    if to_robot or sensor.to_robot:
        return distance_m
    origin = sensor.pose.place(np.zeros((1, 3)))[0]
    return max(0.0, distance_m - body.reach(origin))
