"""The operator: calibration (``operator/calibration``), the signals the task waits for
(``operator/signal``) and the operator's errors (``operator/error``, for the error rate ε)."""

from __future__ import annotations

from schemas.base import Message, PositiveFloat


class Calibration(Message, frozen=True, tag="operator.calibration.v1"):
    """Resting mean RR and its spread for one subject (paper §III-B); stress values derive from them."""

    subject: str
    rr_rest_s: PositiveFloat
    sigma_rest_s: PositiveFloat = 0.14
    rr_stress_offset_s: PositiveFloat = 0.08
    sigma_stress_s: PositiveFloat = 0.08


class OperatorSignal(Message, frozen=True, tag="operator.signal.v1"):
    """The operator (a button, a light curtain, the twin) says something the task waits for
    (``wait_for`` in the task program): ``name`` is that step's name, e.g. ``part_a2``."""

    name: str


class OperatorError(Message, frozen=True, tag="operator.error.v1"):
    """An error the operator made (a quality check, a button, the twin); ``cycle`` is the robot's cycle
    it happened in, when known."""

    cycle: int | None = None
    description: str = ""
