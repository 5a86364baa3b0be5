"""The operator: calibration (``operator/calibration``), the signals the task waits for
(``operator/signal``) and the operator's errors (``operator/error``, for the error rate ε)."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from schemas.base import Message, Name, NonNegInt, RrSeconds, Text

# σ_r, σ_s and the RR_s offset: tenths of a second in the paper; never a second or more
Spread = Annotated[float, msgspec.Meta(gt=0.0, lt=1.0)]
SignalName = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]


# rest: seated at rest, as the paper calibrates; working: at the task at its slowest solution (k = 1)
Posture = Literal["rest", "working"]


class Calibration(Message, frozen=True, tag="operator.calibration.v1"):
    """The baseline mean RR (RR_r) and its spread for one subject (paper §III-B); stress values derive
    from them. ``rr_rest_s`` is the baseline the decision uses, taken in ``posture``: at rest as the
    paper does, or at work (standing and moving lower RR as much as a maths test, so a worker
    calibrated seated who stands to work is read as stressed). A working calibration keeps the level
    at rest it replaced in ``rr_resting_s``."""

    subject: Name
    rr_rest_s: RrSeconds
    sigma_rest_s: Spread = 0.14
    rr_stress_offset_s: Spread = 0.08
    sigma_stress_s: Spread = 0.08
    posture: Posture = "rest"  # new fields: old decoders skip them
    rr_resting_s: RrSeconds | None = None
    # the movement in the calibration's windows (mean and spread of their movement_mg), when the strap
    # sent its accelerometer: a working calibration's is the task's own level of movement
    movement_mg: Annotated[float, msgspec.Meta(ge=0.0, le=32_000.0)] | None = None
    movement_sd_mg: Annotated[float, msgspec.Meta(ge=0.0, le=32_000.0)] | None = None

    def __post_init__(self) -> None:
        if self.rr_rest_s - self.rr_stress_offset_s - self.sigma_stress_s <= 0:
            raise ValueError("RR_r minus the stress offset and σ_s leaves no positive RR_s^max")


class OperatorSignal(Message, frozen=True, tag="operator.signal.v1"):
    """The operator (a button, a light curtain, the twin) says something the task waits for
    (``wait_for`` in the task program): ``name`` is that step's name, e.g. ``part_a2``."""

    name: SignalName
    source: Name | None = None  # who said it: "twin", "cli" (`cadence signal`), an HMI's name


# wrong_object: the wrong part placed; late: a part not there in time to be picked; other: anything else
# "undo": the experimenter withdraws their last mark (`cadence mark undo`): it counts for nothing itself
ErrorKind = Literal["wrong_object", "late", "other", "undo"]


class OperatorError(Message, frozen=True, tag="operator.error.v1"):
    """An error the operator made (a quality check, a button, the twin); ``cycle`` is the robot's cycle
    it happened in, when known."""

    cycle: NonNegInt | None = None
    description: Text = ""
    kind: ErrorKind = "other"
    source: Name | None = None  # who saw it: "twin", "experimenter" (`cadence mark error`)


Coordinate = Annotated[float, msgspec.Meta(ge=-100.0, le=100.0)]
Point = tuple[Coordinate, Coordinate, Coordinate]
MAX_POINTS = 64  # a person's nearest points per reading: a few body parts, a cluster's hull


class Separation(Message, frozen=True, tag="operator.separation.v1"):
    """Where the nearest person is, for speed and separation monitoring (ISO/TS 15066), from a sensor: the
    twin in simulation; in a cell a safety laser scanner's or a camera's adapter (README, "Separation").
    ``t_ns`` is when it was measured; ``age_s`` how old the measurement already was then (the sensor's own
    latency), so a reader's age of it is ``now − t_ns + age_s``.

    What it says, most precise first (common/safety/geometry.py): ``points``, the person's nearest points
    in the sensor's frame (or the cell's, ``placed``), from which the executor finds the distance to the
    arm and its tool; else ``distance_m`` measured to the robot already (``to_robot``, or declared so for
    the source); else ``distance_m`` is a range from the sensor, and the executor reads it on the safe
    side. With points, ``distance_m`` is the sensor's own range to the nearest of them (for a reader that
    knows nothing of points). A sensor that sees nobody says its range and no points."""

    distance_m: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)]
    source: Name
    age_s: Annotated[float, msgspec.Meta(ge=0.0, le=60.0)] = 0.0
    # new fields: old decoders skip them
    points: Annotated[tuple[Point, ...], msgspec.Meta(max_length=MAX_POINTS)] = ()
    to_robot: bool = False
    placed: bool = False  # the points are in the cell frame already (the adapter placed them)
