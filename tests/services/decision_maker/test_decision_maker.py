"""The decision maker as a service, on the in-memory bus (its ports, decoding and graph checks are the real
bus's): answers every window, holds without calibration, and goes on after a restart exactly where an
uninterrupted run would be."""

from __future__ import annotations

import asyncio
import random
from pathlib import Path

import msgspec
import pytest

from common.decision import Params
from schemas import Calibration, HrvWindow, RobotState, Selection
from schemas.topology import AnyMessage
from services.decision_maker.__main__ import Settings, main
from services.decision_maker.state import STATE_FILE
from tests.support.cell import Cell, InProcessService, now_ns, put
from tests.support.decisions import answer, expected, window

pytestmark = pytest.mark.asyncio
S = 1_000_000_000


def start_decider(data: Path, cell: Cell, settings: Settings) -> InProcessService:
    return cell.service("decision_maker", main, settings, data)


async def first_selection(sub) -> Selection:
    async with asyncio.timeout(10):
        _, sel = await anext(sub)
    return sel


def sequence(seed: int, n: int) -> list[HrvWindow]:
    rng = random.Random(seed)
    rr, out = 0.85, []
    for i in range(n):
        rr = min(1.2, max(0.5, rr + rng.choice([-0.06, -0.04, -0.03, -0.01, 0.0, 0.01, 0.02, 0.05])))
        quality = "low" if rng.random() < 0.1 else "good"
        out.append(window(i, round(rr, 3), quality))
    return out


async def test_a_restart_mid_sequence_gives_the_same_k_sequence(tmp_path: Path, cell: Cell) -> None:
    windows = sequence(7, 40)
    settings = Settings(rr_rest_s=0.85, republish_s=0.2)
    async with cell.session() as bus:
        sub = aiter(bus.subscribe(bus.key("decision/selection"), Selection))
        svc = start_decider(tmp_path, cell, settings)
        first = await first_selection(sub)
        assert (first.k, first.reason) == (8, "initial")
        got = [(await answer(bus, sub, w)).k for w in windows[:17]]
        await svc.close()

        svc = start_decider(tmp_path, cell, settings)
        resumed = await first_selection(sub)
        assert resumed.k == got[-1]
        # a window answered before the restart is not stepped again
        put(bus, bus.key("hrv/window"), windows[16], block=True)
        got += [(await answer(bus, sub, w)).k for w in windows[17:]]
        await svc.close()
    assert got == expected(windows, 0.85)
    assert len(set(got)) > 3, "the sequence should move k"


async def test_without_calibration_it_publishes_nothing_until_one_arrives(tmp_path: Path, cell: Cell) -> None:
    async with cell.session() as bus:
        sub = aiter(bus.subscribe(bus.key("decision/selection"), Selection))
        health = aiter(bus.subscribe(bus.key("health/decision_maker"), AnyMessage, maxsize=1))
        svc = start_decider(tmp_path, cell, Settings(republish_s=0.1))
        async with asyncio.timeout(10):
            async for _, status in health:
                if status.state == "waiting for calibration":
                    break
        async with asyncio.timeout(10):
            while not (replies := await bus.get(bus.key("decision/selection"), Selection, timeout=1.0)):
                pass
        assert replies[0].message is None
        assert "no calibration" in replies[0].error
        cal = Calibration(t_ns=1, seq=0, subject="s01", rr_rest_s=0.9)
        await svc.listening(bus, "operator/calibration")  # then one put reaches it: no resending on a timer
        put(bus, bus.key("operator/calibration"), cal, block=True)
        sel = await first_selection(sub)
        assert (sel.k, sel.reason) == (8, "initial")
        # the thresholds it decides against travel with it (Foxglove plots them beside RR)
        thresholds = (sel.rr_rest_s, sel.rr_stress_s, sel.rr_stress_max_s)
        assert thresholds == pytest.approx((0.90, 0.82, 0.74))  # RR_r; - 0.08 offset; - 0.08 sigma_s
        low = await answer(bus, sub, window(0, 0.5, quality="low"))
        assert (low.k, low.delta, low.reason) == (8, 0, "low-quality")
        drop = await answer(bus, sub, window(1, 0.86))  # ΔRR = -0.04 from RR_r = 0.90: one step
        assert (drop.k, drop.delta, drop.reason) == (7, -1, "stress")
        await svc.close()


@pytest.mark.parametrize(("fixed_k", "k"), [("a", 15), ("b", 1), (4, 4)])
async def test_a_fixed_condition_holds_its_k_whatever_the_windows_say(
    tmp_path: Path, cell: Cell, fixed_k: int | str, k: int
) -> None:
    """The study's conditions (a) and (b): one k, published as any selection is, with its own reason;
    windows are counted, not answered, and the adaptive state on disk is not touched."""
    async with cell.session() as bus:
        svc = start_decider(
            tmp_path, cell, Settings(republish_s=0.1, rr_rest_s=0.9, mode="fixed", fixed_k=fixed_k)
        )
        await svc.listening(bus, "hrv/window")
        sub = aiter(bus.subscribe(bus.key("decision/selection"), Selection))
        first = await first_selection(sub)
        assert (first.k, first.n, first.delta, first.reason) == (k, 15, 0, "fixed")
        assert first.rr_stress_s is None  # a fixed k is decided against nothing
        for i, rr in enumerate((0.6, 0.55, 1.1)):  # stress, more stress, rest: Alg. 1 would move k
            put(bus, bus.key("hrv/window"), window(i, rr), block=True)
        async with asyncio.timeout(10):
            while svc.ctx.counters["windows"] < 3:
                await first_selection(sub)  # each republish is a chance to see the count rise
        replies = await bus.get(bus.key("decision/selection"), Selection, timeout=5.0)
        assert replies
        assert replies[0].message == first  # the same selection: nothing moved it
        await svc.close()
    assert not (tmp_path / "decision_state.json").exists()


async def test_a_fixed_k_above_n_is_refused_at_start() -> None:
    with pytest.raises(msgspec.ValidationError, match="outside 1"):
        msgspec.convert({"n": 15, "mode": "fixed", "fixed_k": 16}, Settings)


async def test_a_session_sets_the_condition_and_a_restart_stays_in_it(tmp_path: Path, cell: Cell) -> None:
    """`cadence session` switches conditions on a running decision maker (decision/condition); the reply is
    the selection the condition starts with, stamped with the data time it took effect; condition (c)
    starts Alg. 1 again from the initial k; a restarted service keeps the condition, not the config's."""
    settings = Settings(republish_s=0.1, rr_rest_s=0.9)
    async with cell.session() as bus:
        svc = start_decider(tmp_path, cell, settings)
        await svc.listening(bus, "hrv/window")
        selections = bus.subscribe(bus.key("decision/selection"), Selection)
        sub = aiter(selections)
        assert (await answer(bus, sub, window(0, 0.80))).k == 4  # stressed: k moved from the initial 8

        async def ask(parameters: str) -> Selection | str:
            """A restarted service's queryable reaches this session a little after it starts publishing
            (seen under load): a query before that finds nobody and ends at once, so ask until it answers."""
            selector = bus.key("decision/condition") + f"?{parameters}"
            async with asyncio.timeout(10):
                while not (replies := await bus.get(selector, Selection)):
                    await asyncio.sleep(0.05)
            assert len(replies) == 1
            return replies[0].message or str(replies[0].error)

        before = now_ns()
        a = await ask("mode=fixed;k=a;by=session s1/a")
        assert isinstance(a, Selection)
        assert (a.k, a.reason) == (15, "fixed")
        assert a.t_ns >= before
        assert "k=16" in str(await ask("mode=fixed;k=16"))
        assert "mode='turbo'" in str(await ask("mode=turbo"))
        await svc.close()
        await cell.network.settle()  # what the first service republished is delivered, and read: the
        while selections.pending:  # next is the restarted one's (a loaded host once left a 'stress' queued)
            await selections.receive(1)

        svc = start_decider(tmp_path, cell, settings)  # restarted mid-session: still (a)
        await svc.listening(bus, "hrv/window")
        assert (await first_selection(sub)).reason == "fixed"
        # a session that has just calibrated names its calibration; until it arrives: "not received yet"
        fresh = Calibration(t_ns=now_ns(), seq=0, subject="s1", rr_rest_s=0.95)
        assert "not received yet" in str(await ask(f"mode=adaptive;calibration={fresh.t_ns}"))
        put(bus, bus.key("operator/calibration"), fresh, block=True)
        async with asyncio.timeout(10):  # the topic and the query travel apart: ask until it has come
            while isinstance(c := await ask(f"mode=adaptive;calibration={fresh.t_ns};by=session s1/c"), str):
                assert "not received yet" in c
        assert isinstance(c, Selection)
        assert (c.k, c.reason) == (8, "initial")  # from the initial k again
        assert '"rr_rest_s": 0.95' in (tmp_path / "decision_state.json").read_text()  # of the new RR_r
        assert (await answer(bus, sub, window(1, 0.90))).reason != "fixed"
        await svc.close()


async def test_windows_missed_while_it_was_down_or_stopped_are_asked_for_and_decided_in_order(
    tmp_path: Path, cell: Cell
) -> None:
    """A window published while the decision maker restarted (or was stopped) was never decided, and the
    next step was +3 in one go (issue 40). The analyser keeps its last windows and answers for them
    (stood in for here by a queryable with the same answers); the decision maker asks at start and when
    a window comes after a gap, and decides each in order."""
    from common.runtime.bus import QueryError, Request

    windows = [window(i, rr) for i, rr in enumerate([0.85, 0.80, 0.74, 0.69, 0.66, 0.72])]
    settings = Settings(rr_rest_s=0.85, republish_s=60)

    async def analyser(req: Request) -> HrvWindow:  # what the analyser's window_after answers
        after = int(req.params["after"])
        for w in published:
            if w.end_ns > after:
                return w
        raise QueryError("no window after it")

    published: list[HrvWindow] = []
    async with cell.session() as bus:
        bus.serve(bus.key("hrv/window"), analyser)
        sels = aiter(bus.subscribe(bus.key("decision/selection"), Selection, maxsize=1000))
        svc = start_decider(tmp_path, cell, settings)
        await svc.listening(bus, "hrv/window")

        async def send(w: HrvWindow) -> None:
            published.append(w)
            put(bus, bus.key("hrv/window"), w, block=True)

        async def answered(end_ns: int) -> Selection:
            async with asyncio.timeout(10):
                async for _, sel in sels:
                    if sel.window_end_ns == end_ns:
                        return sel
            raise AssertionError("unreachable")

        got = []
        for w in windows[:2]:
            await send(w)
            got.append((await answered(w.end_ns)).k)
        await svc.close()
        published.append(windows[2])  # published while it was down: nobody heard it
        svc = start_decider(tmp_path, cell, settings)  # it asks at start
        got.append((await answered(windows[2].end_ns)).k)
        await svc.listening(bus, "hrv/window")
        published.append(windows[3])  # lost on the way (a freeze): it asks when the next one comes
        await send(windows[4])
        got += [(await answered(windows[3].end_ns)).k, (await answered(windows[4].end_ns)).k]
        await send(windows[5])
        got.append((await answered(windows[5].end_ns)).k)
        await svc.close()
    assert got == expected(windows, 0.85)


async def test_the_personal_mode_resumes_its_state_after_a_restart(tmp_path: Path, cell: Cell) -> None:
    """Every guarantee the service gives Alg. 1 holds for the personal mode: its state (the reference and
    the recent mean RR beside k) is persisted and resumed, and k stays within 1 … N."""
    from common.decision import Personal, PersonalState, personal_step

    windows = [window(i, rr) for i, rr in enumerate([0.85, 0.80, 0.76, 0.74, 0.80, 0.88])]
    settings = Settings(rr_rest_s=0.85, republish_s=60, decide="personal")
    got = []
    async with cell.session() as bus:
        sels = aiter(bus.subscribe(bus.key("decision/selection"), Selection, maxsize=1000))
        for part in (windows[:3], windows[3:]):  # a restart between them
            svc = start_decider(tmp_path, cell, settings)
            await svc.listening(bus, "hrv/window")
            for w in part:
                got.append((await answer(bus, sels, w)).k)
            await svc.close()
    p, q = Params.of(0.85), Personal()
    s, want = PersonalState.initial(p), []
    for w in windows:
        s = personal_step(p, q, s, w.mean_rr_s, w.n_beats, True)[0]
        want.append(s.k)
    assert got == want
    assert got[0] > got[3] < got[5]  # steps down under load and back up after it


def applied(seq: int) -> RobotState:
    """The executor's state, saying the seq of the selection in force there."""
    return RobotState(t_ns=now_ns(), seq=0, q=[0.0] * 6, qd=[0.0] * 6, tcp=[0.0] * 6, selection_seq=seq)


async def renumbered(sub, seq: int) -> Selection:
    """The first selection not numbered ``seq`` (past the republishing of the one that is)."""
    async with asyncio.timeout(10):
        async for _, sel in sub:
            if sel.seq != seq:
                return sel
    raise AssertionError("unreachable")


async def test_a_seq_in_force_past_its_own_is_passed_at_once_and_a_restart_without_state_numbers_after_it(
    tmp_path: Path, cell: Cell
) -> None:
    """Issue 74: a rogue with this account took the seq in force (the executor's robot/state says which), or
    the state file was moved aside and the decider restarted from seq 1, which the executor refused for
    good. It says its current selection again at once, numbered after the seq in force and stamped now;
    its next decision is numbered after that."""
    settings = Settings(rr_rest_s=0.85, republish_s=0.2)
    async with cell.session() as bus:
        sub = aiter(bus.subscribe(bus.key("decision/selection"), Selection))
        svc = start_decider(tmp_path, cell, settings)
        first = await first_selection(sub)
        put(bus, bus.key("robot/state"), applied(first.seq), block=True)  # its own: nothing to do
        w = window(0, 0.85)
        decided = await answer(bus, sub, w)
        assert decided.seq == first.seq + 1
        put(bus, bus.key("robot/state"), applied(decided.seq + 7), block=True)  # a rogue's, in force
        again = await renumbered(sub, decided.seq)
        assert (again.seq, again.k, again.reason) == (decided.seq + 8, decided.k, decided.reason)
        assert again.t_ns > decided.t_ns
        assert (await answer(bus, sub, window(1, 0.85))).seq == decided.seq + 9
        await svc.close()

        (tmp_path / STATE_FILE).unlink()  # moved aside: the decider starts from nothing
        svc = start_decider(tmp_path, cell, settings)
        restarted = await first_selection(sub)
        assert restarted.seq == 1  # it cannot know yet
        put(bus, bus.key("robot/state"), applied(decided.seq + 9), block=True)
        again = await renumbered(sub, 1)
        assert (again.seq, again.k) == (decided.seq + 10, restarted.k)
        await svc.close()
