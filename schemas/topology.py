"""The bus's topology, declared once (DESIGN §3; dora's dataflow.yml): for every key expression under
``cadence/<cell>/``, the message it carries, who sends it and how. Services, the zenoh-cli decoder and the
tests all read this table; a test checks that publishers and subscribers agree with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import msgspec

from schemas.base import Message
from schemas.decision import Selection
from schemas.ecg import EcgChunk, RrIntervals
from schemas.health import ServiceStatus
from schemas.hrv import Beats, HrvWindow
from schemas.operator import Calibration, OperatorError, OperatorSignal
from schemas.pareto import ParetoSet, ParetoSolutionReply, PlanProgress
from schemas.robot import CycleReport, RobotEvent, RobotState

ROOT = "cadence"
DEFAULT_CELL = "cell1"

Pattern = Literal["topic", "query"]
QoS = Literal["reliable", "block", "drop"]


@dataclass(frozen=True, slots=True)
class Topic:
    suffix: str  # under cadence/<cell>/; '*' matches one chunk
    message: type[Message]
    publisher: str
    pattern: Pattern
    qos: QoS
    also: tuple[str, ...] = ()  # other services that may publish it (the router's ACL: common/cell.py)


TOPICS: tuple[Topic, ...] = (
    Topic("ecg/samples", EcgChunk, "ecg_gateway", "topic", "reliable"),
    Topic("ecg/rr", RrIntervals, "ecg_gateway", "topic", "reliable"),
    Topic("hrv/beats", Beats, "hrv_analyser", "topic", "reliable"),
    Topic("hrv/window", HrvWindow, "hrv_analyser", "topic", "block"),
    Topic("operator/calibration", Calibration, "calibrate", "topic", "reliable"),
    # the operator's HMI, or the operator twin inside the ECG gateway (source = "twin")
    Topic("operator/signal", OperatorSignal, "operator", "topic", "reliable", also=("ecg_gateway",)),
    Topic("operator/error", OperatorError, "operator", "topic", "reliable", also=("ecg_gateway",)),
    Topic("decision/selection", Selection, "decision_maker", "topic", "block"),
    Topic("pareto/progress", PlanProgress, "pareto_store", "topic", "drop"),
    Topic("pareto/*", ParetoSet, "pareto_store", "query", "reliable"),
    Topic("pareto/*/*", ParetoSolutionReply, "pareto_store", "query", "reliable"),
    Topic("robot/state", RobotState, "executor", "topic", "drop"),
    Topic("robot/cycle", CycleReport, "executor", "topic", "reliable"),
    Topic("robot/event", RobotEvent, "executor", "topic", "reliable"),
    # clear a latched stop (`cadence robot resume`): the reply is the state change it made
    Topic("robot/resume", RobotEvent, "executor", "query", "reliable"),
    Topic("health/*", ServiceStatus, "every service", "topic", "drop"),
)

# Every message type, as one tagged union: what a generic reader (the zenoh-cli decoder) accepts.
AnyMessage = (
    EcgChunk
    | RrIntervals
    | Beats
    | HrvWindow
    | Calibration
    | OperatorSignal
    | OperatorError
    | Selection
    | PlanProgress
    | ParetoSet
    | ParetoSolutionReply
    | RobotState
    | CycleReport
    | RobotEvent
    | ServiceStatus
)


def key(cell: str, suffix: str) -> str:
    return f"{ROOT}/{cell}/{suffix}"


def _matches(pattern: str, suffix: str) -> bool:
    a, b = pattern.split("/"), suffix.split("/")
    return len(a) == len(b) and all(p in ("*", s) for p, s in zip(a, b, strict=True))


def topic_of(key_expr: str) -> Topic | None:
    """The topic a concrete key (``cadence/<cell>/…``) belongs to; the first exact match wins."""
    parts = key_expr.split("/", 2)
    if len(parts) < 3 or parts[0] != ROOT:
        return None
    suffix = parts[2]
    exact = [t for t in TOPICS if t.suffix == suffix]
    if exact:
        return exact[0]
    return next((t for t in TOPICS if _matches(t.suffix, suffix)), None)


_ANY_DECODER = msgspec.msgpack.Decoder(AnyMessage)
_ENCODER = msgspec.msgpack.Encoder()


def encode(msg: Message) -> bytes:
    return _ENCODER.encode(msg)


def decode_any(payload: bytes) -> Message:
    """Decode any Cadence message by its tag; raises ``msgspec.ValidationError``/``DecodeError``."""
    return _ANY_DECODER.decode(payload)
