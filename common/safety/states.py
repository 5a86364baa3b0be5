"""The executor's safety states as a pure transition function (DESIGN §9; docs/robot.md, "The executor").

Why explicit: the executor is the only service that moves the robot, and the question "may it move now,
and if not, why not" must have one answer that an operator can read off the bus. Every state change is
published (``robot/state`` carries the state, ``robot/event`` each change). The rules that matter:

- Motion starts only from ``ready`` (``MOVE`` anywhere else raises ``IllegalTransition``): the robot
  never moves without a connected arm, a current selection and a set, and never while stopped.
- A fault (a protective stop for limits or overruns, a lost controller) is a latch: ``stopped`` ignores
  everything but ``RESUME`` (and ``SHUTDOWN``). Only ``RECOVERED``, after the backend cleared the fault,
  leaves it, through ``recovering``.
- Without a current selection the executor waits for one (``waiting_for_selection``); having one is
  remembered across every state, so a selection that came during a stop is not lost.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum


class State(StrEnum):
    STARTING = "starting"
    WAITING_FOR_ROBOT = "waiting_for_robot"
    WAITING_FOR_SELECTION = "waiting_for_selection"
    WAITING_FOR_SET = "waiting_for_set"
    READY = "ready"
    MOVING = "moving"
    WAITING_FOR_OPERATOR = "waiting_for_operator"
    REFUSED = "refused"
    STOPPED = "stopped"
    RECOVERING = "recovering"
    OFF = "off"


class Event(StrEnum):
    CONNECTED = "connected"  # the backend is up
    DISCONNECTED = "disconnected"  # it could not be reached (at start)
    SELECTION = "selection"  # a current selection is known
    SET_MISSING = "set_missing"  # the next path has no set
    SET_READY = "set_ready"
    REFUSE = "refuse"  # the next trajectory, or the arm's pose, was refused
    CHANGED = "changed"  # something that may resolve a refusal (a selection, a set, a while)
    MOVE = "move"  # a motion is handed to the robot
    DONE = "done"  # it ended at its target
    WAIT_OPERATOR = "wait_operator"
    OPERATOR = "operator"  # the signal waited for came
    FAULT = "fault"  # a protective stop, overruns, a lost controller
    RESUME = "resume"  # a person (or the sim's automatic policy) asks to clear the fault
    RECOVERED = "recovered"  # the backend cleared it
    RECOVERY_FAILED = "recovery_failed"
    SHUTDOWN = "shutdown"


class IllegalTransition(RuntimeError):
    """Asked to move from a state that may not: the motion must not start."""


@dataclass(frozen=True, slots=True)
class Motion:
    state: State = State.STARTING
    reason: str = ""  # why the robot is in this state (a stop's cause, what it waits for)
    has_selection: bool = False

    @property
    def may_move(self) -> bool:
        return self.state is State.READY


def _ready_or_waiting(m: Motion, reason: str = "") -> Motion:
    if m.has_selection:
        return replace(m, state=State.READY, reason=reason)
    return replace(m, state=State.WAITING_FOR_SELECTION, reason="no current selection")


# (state, event) -> next state, for the transitions that do not depend on a guard
_TABLE: dict[tuple[State, Event], State] = {
    (State.STARTING, Event.DISCONNECTED): State.WAITING_FOR_ROBOT,
    (State.READY, Event.SET_MISSING): State.WAITING_FOR_SET,
    (State.READY, Event.REFUSE): State.REFUSED,
    (State.READY, Event.MOVE): State.MOVING,
    (State.READY, Event.WAIT_OPERATOR): State.WAITING_FOR_OPERATOR,
    (State.WAITING_FOR_SET, Event.REFUSE): State.REFUSED,
    (State.REFUSED, Event.SET_MISSING): State.WAITING_FOR_SET,
    (State.STOPPED, Event.RESUME): State.RECOVERING,
    (State.RECOVERING, Event.RECOVERY_FAILED): State.STOPPED,
}
# events that leave a state for ready (or waiting_for_selection when there is none)
_TO_READY: dict[State, set[Event]] = {
    State.STARTING: {Event.CONNECTED},
    State.WAITING_FOR_ROBOT: {Event.CONNECTED},
    State.WAITING_FOR_SELECTION: {Event.SELECTION},
    State.WAITING_FOR_SET: {Event.SET_READY},
    State.REFUSED: {Event.CHANGED, Event.SET_READY, Event.SELECTION},
    State.MOVING: {Event.DONE},
    State.WAITING_FOR_OPERATOR: {Event.OPERATOR},
    State.RECOVERING: {Event.RECOVERED},
}


def transition(m: Motion, event: Event, reason: str = "") -> Motion:
    """The state after ``event``; unchanged when the event means nothing in this state."""
    if event is Event.MOVE and not m.may_move:
        raise IllegalTransition(f"no motion in state {m.state}" + (f" ({m.reason})" if m.reason else ""))
    if m.state is State.OFF:
        return m
    if event is Event.SHUTDOWN:
        return Motion(State.OFF, reason or "shut down", m.has_selection)
    if event is Event.SELECTION:
        m = replace(m, has_selection=True)
    if event is Event.FAULT and m.state is not State.STOPPED:
        return replace(m, state=State.STOPPED, reason=reason or "protective stop")
    if m.state is State.STOPPED:  # the latch: only RESUME leaves it
        return replace(m, state=State.RECOVERING, reason=reason) if event is Event.RESUME else m
    if event in _TO_READY.get(m.state, set()):
        return _ready_or_waiting(m, reason)
    nxt = _TABLE.get((m.state, event))
    if nxt is not None:
        return replace(m, state=nxt, reason=reason)
    return m


_ROUTINE = {State.READY.value, State.MOVING.value, State.WAITING_FOR_OPERATOR.value}
_MODE = {
    State.MOVING: "moving",
    State.WAITING_FOR_OPERATOR: "waiting",
    State.WAITING_FOR_SET: "waiting",
    State.REFUSED: "refused",
    State.STOPPED: "fault",
    State.RECOVERING: "recovering",
}


def mode_of(state: State) -> str:
    """``robot/state``'s coarse ``mode``, derived from the one safety state (kept for its readers)."""
    return _MODE.get(state, "idle")


def routine_change(from_state: str | None, to_state: str | None) -> bool:
    """A ``robot/event`` of kind "state" between the states of normal work (ready, moving, waiting for
    the operator): every path gives two, so a report or a live view leaves them out."""
    return from_state in _ROUTINE and to_state in _ROUTINE


def idle_spans(events: Sequence[Mapping[str, object]], end_s: float) -> list[tuple[float, float, str]]:
    """(start, end, state) of each span in which the robot was out of normal work (stopped, recovering,
    waiting for a selection …), from the ``robot/event`` state changes of a run (``t_s`` and ``to``, the
    state entered), so that a figure never shows adaptation that did not move the arm. A span
    still open at the end closes at ``end_s``."""
    spans: list[tuple[float, float, str]] = []
    open_at: tuple[float, str] | None = None
    for e in sorted((e for e in events if e.get("kind") == "state"), key=lambda e: float(str(e["t_s"]))):
        if e.get("to") is None:
            continue
        t, to = float(str(e["t_s"])), str(e["to"])
        if to in _ROUTINE:
            if open_at is not None:
                spans.append((open_at[0], t, open_at[1]))
                open_at = None
        elif open_at is None:
            open_at = (t, to)
    if open_at is not None and end_s > open_at[0]:
        spans.append((open_at[0], end_s, open_at[1]))
    return spans
