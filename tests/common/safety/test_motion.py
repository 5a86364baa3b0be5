"""The executor's safety states (common/safety/states.py): every transition, and the two rules that matter:
no motion but from ready, and a stop is a latch only RESUME opens."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from common.safety.states import Event, IllegalTransition, Motion, State, transition
from services.executor.cores import claim_core

E, St = Event, State
# every (state, event) that changes the state, with the state it leads to; with a selection known
WITH_SELECTION = {
    (St.STARTING, E.CONNECTED): St.READY,
    (St.STARTING, E.DISCONNECTED): St.WAITING_FOR_ROBOT,
    (St.WAITING_FOR_ROBOT, E.CONNECTED): St.READY,
    (St.WAITING_FOR_SELECTION, E.SELECTION): St.READY,
    (St.WAITING_FOR_SET, E.SET_READY): St.READY,
    (St.WAITING_FOR_SET, E.REFUSE): St.REFUSED,
    (St.READY, E.SET_MISSING): St.WAITING_FOR_SET,
    (St.READY, E.REFUSE): St.REFUSED,
    (St.READY, E.MOVE): St.MOVING,
    (St.READY, E.WAIT_OPERATOR): St.WAITING_FOR_OPERATOR,
    (St.MOVING, E.DONE): St.READY,
    (St.WAITING_FOR_OPERATOR, E.OPERATOR): St.READY,
    (St.REFUSED, E.CHANGED): St.READY,
    (St.REFUSED, E.SET_READY): St.READY,
    (St.REFUSED, E.SELECTION): St.READY,
    (St.REFUSED, E.SET_MISSING): St.WAITING_FOR_SET,
    (St.STOPPED, E.RESUME): St.RECOVERING,
    (St.RECOVERING, E.RECOVERED): St.READY,
    (St.RECOVERING, E.RECOVERY_FAILED): St.STOPPED,
}
for s in St:
    if s not in (St.STOPPED, St.OFF):
        WITH_SELECTION[(s, E.FAULT)] = St.STOPPED
    if s is not St.OFF:
        WITH_SELECTION[(s, E.SHUTDOWN)] = St.OFF


@pytest.mark.parametrize(("state", "event"), list(itertools.product(St, E)), ids=lambda x: str(x))
def test_every_state_and_event_with_a_selection(state: State, event: Event) -> None:
    m = Motion(state, "why", has_selection=True)
    if event is E.MOVE and state is not St.READY:
        with pytest.raises(IllegalTransition):
            transition(m, event)
        return
    assert transition(m, event, "because").state is WITH_SELECTION.get((state, event), state)


@pytest.mark.parametrize(
    "state", [St.STARTING, St.WAITING_FOR_ROBOT, St.WAITING_FOR_SET, St.REFUSED, St.MOVING, St.RECOVERING]
)
def test_without_a_selection_what_would_be_ready_waits_for_one(state: State) -> None:
    event = {
        St.STARTING: E.CONNECTED,
        St.WAITING_FOR_ROBOT: E.CONNECTED,
        St.WAITING_FOR_SET: E.SET_READY,
        St.REFUSED: E.CHANGED,
        St.MOVING: E.DONE,
        St.RECOVERING: E.RECOVERED,
    }[state]
    m = transition(Motion(state), event)
    assert (m.state, m.reason) == (St.WAITING_FOR_SELECTION, "no current selection")
    assert transition(m, E.SELECTION).state is St.READY


def test_a_stop_is_a_latch_that_keeps_its_reason_and_remembers_a_selection() -> None:
    m = transition(Motion(St.MOVING), E.FAULT, "5 overruns in a row")
    for e in E:
        if e in (E.RESUME, E.SHUTDOWN, E.MOVE):
            continue
        m = transition(m, e, "other")
        assert (m.state, m.reason) == (St.STOPPED, "5 overruns in a row")
    with pytest.raises(IllegalTransition, match="stopped"):
        transition(m, E.MOVE)
    assert m.has_selection  # the SELECTION that came during the stop
    m = transition(transition(m, E.RESUME, "cadence robot resume"), E.RECOVERED)
    assert m.state is St.READY
    assert m.may_move


def test_off_is_final() -> None:
    m = transition(Motion(St.READY), E.SHUTDOWN)
    assert all(transition(m, e).state is St.OFF for e in E if e is not E.MOVE)


def test_two_executors_on_one_host_get_different_cores_and_a_third_none(tmp_path: Path) -> None:
    a = claim_core([0, 1], tmp_path)
    b = claim_core([0, 1], tmp_path)
    c = claim_core([0, 1], tmp_path)
    assert (a.core, b.core, c.core) == (1, 0, None)
    assert "already serve other executors" in c.note
    a.release()
    d = claim_core([0, 1], tmp_path)  # a stopped executor's core is free again
    assert d.core == 1
    assert claim_core([0, 1], tmp_path, explicit=0).core is None  # an explicit core that is taken
    for x in (b, c, d):
        x.release()


def test_routine_changes_are_told_from_the_ones_a_person_should_see() -> None:
    from common.safety.states import routine_change

    assert routine_change("ready", "moving")
    assert routine_change("moving", "ready")
    assert routine_change("waiting_for_operator", "ready")
    assert not routine_change("moving", "stopped")
    assert not routine_change("recovering", "ready")
    assert not routine_change(None, None)  # not a change


def test_the_coarse_mode_is_derived_from_the_one_safety_state() -> None:
    """robot/state's ``mode`` was a second state the executor set by hand beside ``state`` (issue 30): it
    is now read off the safety state, so the two cannot disagree."""
    from common.safety.states import State, mode_of

    assert mode_of(State.MOVING) == "moving"
    assert mode_of(State.READY) == "idle"
    assert mode_of(State.WAITING_FOR_OPERATOR) == mode_of(State.WAITING_FOR_SET) == "waiting"
    assert (mode_of(State.STOPPED), mode_of(State.RECOVERING), mode_of(State.REFUSED)) == (
        "fault",
        "recovering",
        "refused",
    )
    assert {mode_of(s) for s in State} == {"moving", "idle", "waiting", "fault", "recovering", "refused"}
