"""The bus's graph, declared once (DESIGN §3; dora's dataflow.yml): for every key expression under
``cadence/<cell>/``, the message it carries, the roles that publish it, the roles that read it, the
roles that may ask for it, and how it travels.

Everything else is derived from this table, so nothing can disagree with it:
- a service's ports (``Bus.publisher``, ``Bus.subscribe``, ``Bus.serve``, ``Bus.get``): a service that
  opens a port the graph does not give its role gets a ``BusError`` at start, and a message of another
  type than the key's is a ``TypeError`` at the put;
- the demo's launch order (``launch_order``);
- the router's access control (cadence/deploy/cell.py): each account publishes only its roles' keys;
- the zenoh-cli decoder (cadence/tools/zenoh_codec.py), which decodes each key with its own type;
- the graph test (tests/schemas/test_graph.py), which runs every service and checks what it opened.
"""

from __future__ import annotations

import functools
from collections.abc import Collection
from dataclasses import dataclass, replace
from typing import Any, Generic, Literal, TypeVar

import msgspec

from schemas.base import Message
from schemas.clock import CellClock
from schemas.decision import Selection
from schemas.ecg import AccChunk, EcgChunk, RrIntervals
from schemas.health import ServiceStatus
from schemas.hrv import Beats, HrvWindow
from schemas.operator import Calibration, OperatorError, OperatorSignal, Separation
from schemas.pareto import ParetoSet, ParetoSolutionReply, PlanProgress
from schemas.robot import CycleReport, RobotEvent, RobotState

ROOT = "cadence"
DEFAULT_CELL = "cell1"
# the plant's own keys, beside every cell's (``Topic.scope``): what any cell may ask all the others
PLANT_SCOPE = "plant"

M = TypeVar("M", bound=Message)

Pattern = Literal["topic", "query"]
# block: congestion control BLOCK, a slow reader slows the writer rather than lose a message (low rates);
# drop: a message that cannot be sent now is dropped, the next one replaces it (telemetry, latest wins)
QoS = Literal["block", "drop"]


@dataclass(frozen=True, slots=True)
class Topic(Generic[M]):
    """A key of the graph and how it travels; who publishes, reads and asks it is derived from the
    roles' declarations (``ROLES``), never written here."""

    suffix: str  # under cadence/<cell>/; '*' stands for one chunk, filled in when a port is opened
    message: type[M]
    pattern: Pattern = "topic"
    qos: QoS = "block"
    family: str = ""  # the suffix as declared, wildcards unfilled (a member's, ``at``, is its family's)
    # who numbers its messages: "port", the publishing node's output port (per key, DESIGN §3), or
    # "message", the message itself, when its seq is its identity (a selection's survives a restart and
    # is republished as it was; a window answered again on ``hrv/window?after=`` is the one published)
    numbered: Literal["port", "message"] = "port"
    # "cell": under cadence/<cell>/, the cell's own; "plant": under cadence/plant/, shared by the cells of
    # a plant (sets by hash: one cell asks, any cell that has it answers), where no cell's key is
    scope: Literal["cell", "plant"] = "cell"
    # each member is one account's (``operator/separation/<chunk>``: a declared sensor's own key): the ACL
    # grants a member to its own account only (cadence/deploy/cell.py), never the family to a role
    owned: bool = False

    def __post_init__(self) -> None:
        if not self.family:
            object.__setattr__(self, "family", self.suffix)

    def at(self, *chunks: str) -> Topic[M]:
        """One member of a family (``PARETO_SET.at("b1_to_b2")``): the wildcards filled in order."""
        return replace(self, suffix=fill(self.suffix, chunks))

    @property
    def publishers(self) -> tuple[str, ...]:
        """The roles that publish it (for a query: that answer it)."""
        return _view(self.family)[0]

    @property
    def subscribers(self) -> tuple[str, ...]:
        """The roles that act on it (tools read everything anyway)."""
        return _view(self.family)[1]

    @property
    def askers(self) -> tuple[str, ...]:
        """The roles that may query it (a topic's publisher also answers queries)."""
        return _view(self.family)[2]


ECG_SAMPLES = Topic("ecg/samples", EcgChunk)
ECG_RR = Topic("ecg/rr", RrIntervals)
# the strap's accelerometer: movement, told apart from mental load (a source without one sends none)
ECG_ACC = Topic("ecg/acc", AccChunk)
HRV_BEATS = Topic("hrv/beats", Beats, numbered="message")
HRV_WINDOW = Topic("hrv/window", HrvWindow, numbered="message")
CALIBRATION = Topic("operator/calibration", Calibration)
# the executor publishes a button on one of the controller's digital inputs (a task step's ``input``)
OPERATOR_SIGNAL = Topic("operator/signal", OperatorSignal)
# the executor publishes a part not there by its wait_for step's deadline (kind "late")
OPERATOR_ERROR = Topic("operator/error", OperatorError)
# the nearest person's distance, for the executor's speed and separation monitoring
# (common/safety/separation.py)
OPERATOR_SEPARATION = Topic("operator/separation", Separation, qos="drop")
# … a declared sensor's own key, ``operator/separation/<source_chunk(source)>``: on an installed cell only
# that sensor's account may put it, and the executor takes there only readings under that source's name
OPERATOR_SEPARATION_OF = Topic("operator/separation/*", Separation, qos="drop", owned=True)


def source_chunk(source: str) -> str:
    """A separation source's name as a key chunk and an account's name: what is not a letter, a digit or
    '_' becomes '_' (``scanner:front`` → ``scanner_front``)."""
    return "".join(c if c.isascii() and (c.isalnum() or c == "_") else "_" for c in source)


def sensor_account(source: str) -> str:
    """The bus account of a declared separation source (`cadence install --scanner`)."""
    return f"sensor_{source_chunk(source)}"


SELECTION = Topic("decision/selection", Selection, numbered="message")
# the study condition in force (`cadence session`): mode=fixed;k=a|b|<k> or mode=adaptive (Alg. 1 from the
# initial k); the reply is the selection it starts with, stamped with the data time it took effect
DECISION_CONDITION = Topic("decision/condition", Selection, pattern="query")
# its error reply while a calibration the asker names has not reached the decision maker: ask again
CALIBRATION_NOT_YET = "not received yet"
PLAN_PROGRESS = Topic("pareto/progress", PlanProgress, qos="drop")
PARETO_SET = Topic("pareto/*", ParetoSet, pattern="query")
PARETO_SOLUTION = Topic("pareto/*/*", ParetoSolutionReply, pattern="query")
# a set by the content hash of what it was planned from (waypoints, limits, planner settings), whichever
# cell of the plant planned it: a store asks before it plans, and answers for every set it has
PLANT_SETS = Topic("sets/*", ParetoSet, pattern="query", scope="plant")
ROBOT_STATE = Topic("robot/state", RobotState, qos="drop")
ROBOT_CYCLE = Topic("robot/cycle", CycleReport)
ROBOT_EVENT = Topic("robot/event", RobotEvent)
# clear a latched stop (`cadence robot resume`): the reply is the state change it made
ROBOT_RESUME = Topic("robot/resume", RobotEvent, pattern="query")
HEALTH = Topic("health/*", ServiceStatus, qos="drop")  # health/<service>, plus a liveliness token
# a simulated cell's data clock (the demo answers it): how a tool joining the cell stamps what it says
CELL_CLOCK = Topic("clock", CellClock, pattern="query")


@dataclass(frozen=True, slots=True)
class Role:
    """A node of the graph, declared once: who it is and every port it opens. A service (its own process
    and account) or a tool (``operator``: calibrate, resume, an HMI; ``separation_sensor``: a scanner's
    adapter; ``monitor``: record, top, zenoh subscribe). Every service also publishes its own
    ``health/<service>``, and only that one."""

    name: str
    kind: Literal["service", "tool", "sim"]  # sim: only in a simulated cell, never a deployed account
    reads_all: bool = False  # tools read the whole cell, as the ACL lets everyone
    inputs: tuple[Topic[Any], ...] = ()  # topics it subscribes to and acts on
    outputs: tuple[Topic[Any], ...] = ()  # topics it publishes
    answers: tuple[Topic[Any], ...] = ()  # queries it answers (a published topic's latest, on demand)
    asks: tuple[Topic[Any], ...] = ()  # queries it sends
    # what it does on its own every so often (a node's ``@every``), each by the settings field (or the
    # seconds) that sets its period: the clock a simulated cell drives must know every one of them
    timers: tuple[Timer, ...] = ()


@dataclass(frozen=True, slots=True)
class Timer:
    """A node's periodic work, declared in the graph beside its ports."""

    name: str  # the node's method
    period: str | float  # the settings field that holds the period in seconds, or the seconds


LOOKERS = (SELECTION, PARETO_SET, PARETO_SOLUTION, CELL_CLOCK)  # what tools may ask (`cadence get`)
ROLES: tuple[Role, ...] = (
    Role(
        "pareto_store",
        "service",
        outputs=(PLAN_PROGRESS,),
        answers=(PARETO_SET, PARETO_SOLUTION, PLANT_SETS),
        asks=(PLANT_SETS,),
    ),
    Role(
        "decision_maker",
        "service",
        inputs=(HRV_WINDOW, CALIBRATION, ROBOT_STATE),  # robot/state: the seq in force, to number after it
        outputs=(SELECTION,),
        answers=(SELECTION, DECISION_CONDITION),
        asks=(HRV_WINDOW,),  # the windows it missed while it was down (the analyser keeps its last ones)
        timers=(Timer("current", "republish_s"),),  # the selection in force, again (state, not an event)
    ),
    # ecg/rr is read only with input = rr
    Role(
        "hrv_analyser",
        "service",
        inputs=(ECG_SAMPLES, ECG_RR, ECG_ACC),
        outputs=(HRV_BEATS, HRV_WINDOW),
        answers=(HRV_WINDOW,),
    ),
    Role("ecg_gateway", "service", outputs=(ECG_SAMPLES, ECG_RR, ECG_ACC)),
    Role(
        "executor",
        "service",
        inputs=(SELECTION, OPERATOR_SIGNAL, OPERATOR_SEPARATION, OPERATOR_SEPARATION_OF),
        outputs=(ROBOT_STATE, ROBOT_CYCLE, ROBOT_EVENT, OPERATOR_SIGNAL, OPERATOR_ERROR),
        answers=(ROBOT_RESUME,),
        asks=(SELECTION, PARETO_SET),
        timers=(Timer("scale", "scale_period_s"), Timer("state", "state_period_s")),
    ),
    # the simulated operator (common/sim/twin.py): it watches the robot and is the ECG source of a cell
    # without a strap, in the gateway's place
    Role(
        "operator_twin",
        "service",
        inputs=(ROBOT_STATE, ROBOT_CYCLE, CALIBRATION),
        outputs=(ECG_SAMPLES, ECG_ACC, OPERATOR_SIGNAL, OPERATOR_ERROR, OPERATOR_SEPARATION),
        timers=(Timer("separation", "separation_period_s"),),
    ),
    Role(
        "operator",
        "tool",
        reads_all=True,
        outputs=(CALIBRATION, OPERATOR_SIGNAL, OPERATOR_ERROR),
        asks=(*LOOKERS, DECISION_CONDITION, ROBOT_RESUME),
    ),
    # a cell's safety laser scanners or cameras (`cadence separation`): the only account that may say where
    # people are, beside the twin on a simulated cell; an HMI's operator account cannot free the arm
    Role(
        "separation_sensor",
        "tool",
        reads_all=True,
        outputs=(OPERATOR_SEPARATION, OPERATOR_SEPARATION_OF),
        asks=(CELL_CLOCK,),
    ),
    Role("monitor", "tool", reads_all=True, asks=LOOKERS),
    # `cadence demo`: the simulated cell's router and its clock
    Role("demo", "sim", reads_all=True, answers=(CELL_CLOCK,), asks=LOOKERS),
)
ROLE = {r.name: r for r in ROLES}
SERVICES = tuple(r.name for r in ROLES if r.kind == "service")


@functools.cache
def _view(family: str) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
    """(publishers, subscribers, askers) of a topic, read off the roles' declarations."""

    def having(ports: str) -> tuple[str, ...]:
        return tuple(r.name for r in ROLES if any(p.family == family for p in getattr(r, ports)))

    publishers = (
        SERVICES if family == "health/*" else tuple(dict.fromkeys(having("outputs") + having("answers")))
    )
    return publishers, having("inputs"), having("asks")


TOPICS: tuple[Topic[Any], ...] = (
    ECG_SAMPLES,
    ECG_RR,
    ECG_ACC,
    HRV_BEATS,
    HRV_WINDOW,
    CALIBRATION,
    OPERATOR_SIGNAL,
    OPERATOR_ERROR,
    OPERATOR_SEPARATION,
    OPERATOR_SEPARATION_OF,
    SELECTION,
    DECISION_CONDITION,
    PLAN_PROGRESS,
    PARETO_SET,
    PARETO_SOLUTION,
    PLANT_SETS,
    ROBOT_STATE,
    ROBOT_CYCLE,
    ROBOT_EVENT,
    ROBOT_RESUME,
    HEALTH,
    CELL_CLOCK,
)
# a cell runs one of them: the gateway (a strap, a replay) or the operator twin
ECG_SOURCES = tuple(p for p in ECG_SAMPLES.publishers if p in SERVICES)


def cell_roster(alive: Collection[str]) -> list[str]:
    """The services a cell runs, as a view of it names them: one ECG source for the cell, the one that is
    ``alive`` (or ``ecg_gateway or operator_twin`` while neither is), and every other service."""
    source = next((s for s in ECG_SOURCES if s in alive), " or ".join(ECG_SOURCES))
    return list(dict.fromkeys(source if s in ECG_SOURCES else s for s in SERVICES))


# Every message type, as one tagged union: what a reader of unknown keys accepts.
AnyMessage = (
    EcgChunk
    | AccChunk
    | RrIntervals
    | Beats
    | HrvWindow
    | Calibration
    | OperatorSignal
    | OperatorError
    | Separation
    | Selection
    | PlanProgress
    | ParetoSet
    | ParetoSolutionReply
    | RobotState
    | CycleReport
    | RobotEvent
    | ServiceStatus
    | CellClock
)


def key(cell: str, suffix: str) -> str:
    return f"{ROOT}/{cell}/{suffix}"


def key_for(topic: Topic[Any], cell: str) -> str:
    """A topic's key expression for a cell: under the cell, or under the plant for a plant's topic."""
    return key(PLANT_SCOPE if topic.scope == "plant" else cell, topic.suffix)


def fill(suffix: str, chunks: tuple[str, ...]) -> str:
    """``pareto/*`` with ("b1_to_b2",) → ``pareto/b1_to_b2``; chunks left out stay wildcards."""
    parts = suffix.split("/")
    stars = [i for i, p in enumerate(parts) if p == "*"]
    if len(chunks) > len(stars):
        raise ValueError(f"{suffix}: {len(chunks)} chunks for {len(stars)} wildcards")
    for i, chunk in zip(stars, chunks, strict=False):
        if not chunk or "/" in chunk or "*" in chunk:
            raise ValueError(f"{suffix}: bad key chunk {chunk!r}")
        parts[i] = chunk
    return "/".join(parts)


def _matches(pattern: str, suffix: str) -> bool:
    a, b = pattern.split("/"), suffix.split("/")
    return len(a) == len(b) and all(p in ("*", s) for p, s in zip(a, b, strict=True))


def topic_of(key_expr: str) -> Topic[Any] | None:
    """The topic a concrete key (``cadence/<cell>/…``) belongs to; an exact match wins over a wildcard."""
    parts = key_expr.split("/", 2)
    if len(parts) < 3 or parts[0] != ROOT:
        return None
    suffix = parts[2]
    exact = [t for t in TOPICS if t.suffix == suffix]
    if exact:
        return exact[0]
    return next((t for t in TOPICS if _matches(t.suffix, suffix)), None)


def may_publish(role: str, topic: Topic[Any]) -> bool:
    return role in topic.publishers


def may_subscribe(role: str, topic: Topic[Any]) -> bool:
    r = ROLE.get(role)
    return r is not None and (r.reads_all or role in topic.subscribers)


def may_ask(role: str, topic: Topic[Any]) -> bool:
    r = ROLE.get(role)
    return r is not None and role in topic.askers


def launch_order() -> tuple[str, ...]:
    """The services in the order to start them: after every service that answers their queries, and
    after every service that reads what they publish (Zenoh drops a put with no subscriber yet). Where
    the two disagree (the executor asks the decision maker, and reads what it publishes), the query
    wins; where readers wait on each other (the executor and the operator twin read each other), the
    first declared goes first. Ties keep the declared order."""
    services = set(SERVICES)
    # (before, after) pairs of two services
    must = {(p, a) for t in TOPICS for p in t.publishers for a in t.askers if p != a and {p, a} <= services}
    rather = {
        (s, p)
        for t in TOPICS
        for p in t.publishers
        for s in t.subscribers
        if p != s and {p, s} <= services and (p, s) not in must
    }
    order: list[str] = []
    left = list(SERVICES)
    while left:
        free = [s for s in left if not any(b in left and a == s for b, a in must)]
        ready = [s for s in free if not any(b in left and a == s for b, a in rather)] or free[:1]
        order.append(ready[0])
        left.remove(ready[0])
    return tuple(order)


_ANY_DECODER = msgspec.msgpack.Decoder(AnyMessage)
_ENCODER = msgspec.msgpack.Encoder()


def encode(msg: Message) -> bytes:
    return _ENCODER.encode(msg)


def validated(msg: M) -> M:
    """The message as any receiver will decode it: building a Struct checks nothing, so what a process
    makes itself and sends or stores passes the schema's bounds here first (``msgspec.ValidationError``)."""
    decoded: M = msgspec.msgpack.decode(encode(msg), type=type(msg))
    return decoded


def decode_any(payload: bytes) -> Message:
    """Decode any Cadence message by its tag; raises ``msgspec.ValidationError``/``DecodeError``."""
    msg: Message = _ANY_DECODER.decode(payload)
    return msg
