"""Property-based fuzzing of a whole cell over real Zenoh (docs/operations.md, "Bad input").

Hypothesis draws hostile but well-typed messages for every topic of the topology: an honest message with
one to three fields replaced by values a broken or hostile sender could put there (NaN, ±inf, 1e300,
int64 edges, empty and huge lists and strings, wrong types, None), its data times shifted by days to
years, or bytes that are no message at all. They go to every service of a cell at once, in process over
loopback Zenoh, interleaved with an honest cell's traffic. The properties: every service keeps answering
the honest input exactly as without the fuzz (k is what Alg. 1 gives on the honest windows alone, the
windows are the honest stream's, the robot runs at the honest k), its status keeps coming, no handler
fails, and memory stays bounded. The draws are derandomized: the same messages every run.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from common.decision import Params, State, step
from common.runtime.bus import Bus, BusConfig
from schemas import Calibration, CycleReport, EcgChunk, HrvWindow, ParetoSet, Selection, ServiceStatus
from schemas.topology import TOPICS, Topic
from services.decision_maker.__main__ import Settings as DecisionSettings
from services.decision_maker.__main__ import main as decision_main
from services.decision_maker.state import same_calibration
from services.executor.__main__ import Settings as ExecutorSettings
from services.executor.__main__ import main as executor_main
from services.hrv_analyser.__main__ import Settings as AnalyserSettings
from services.hrv_analyser.__main__ import main as analyser_main
from services.operator_twin.__main__ import Settings as TwinSettings
from services.operator_twin.__main__ import main as twin_main
from tests.support.cell import CELL, InProcessService, now_ns, put
from tests.support.data import DAY, S, chunks, synthetic_ecg
from tests.support.executor import SPEED, TASK, store_serving
from tests.support.messages import SAMPLES

pytestmark = pytest.mark.asyncio

HOSTILE_PER_CHUNK = 10  # hostile messages between two honest ECG chunks: 1,780 over the 178 chunks
YEAR = 365 * DAY

INTS = [-1, 0, 2**31, 2**53 + 1, 2**63 - 1, 2**63, 2**64 - 1, -(2**63)]
FLOATS = [float("nan"), float("inf"), float("-inf"), 1e300, -1e300, 1e-300, -1.0, 0.0, 1e17, 1e9, 3.5, 0.1]
STRINGS = ["", "x" * 10_000, "../../etc/passwd", "\x00", "é" * 300]
LISTS = [[], [None], ["x"], [float("nan")] * 7, [0] * 100_000, [[1e300] * 6] * 3]
DICTS = [{}, {"x" * 300: -1}, {str(i): 1 for i in range(2000)}, {"type": "nope"}]
ANYTHING = [None, True, "text", 1e300, -1, [], {}]


def pool(info: msgspec.inspect.Type) -> list[Any]:
    """Hostile values for a field of this type, and values of every other type."""
    if isinstance(info, msgspec.inspect.UnionType):
        return [v for t in info.types for v in pool(t)]
    base = {
        msgspec.inspect.IntType: INTS,
        msgspec.inspect.FloatType: FLOATS,
        msgspec.inspect.StrType: STRINGS,
        msgspec.inspect.BoolType: [True, False],
        msgspec.inspect.ListType: LISTS,
        msgspec.inspect.DictType: DICTS,
        msgspec.inspect.NoneType: [None],
        msgspec.inspect.LiteralType: STRINGS,
    }.get(type(info), [])
    return base + ANYTHING


def mutations(msg_type: type[msgspec.Struct]) -> st.SearchStrategy:
    """What to do to an honest message: ("fields", [(name, value), …]), ("shift", ns) or ("bytes", b)."""
    info = msgspec.inspect.type_info(msg_type)
    fields = [(f.name, pool(f.type)) for f in info.fields]
    one = st.sampled_from(fields).flatmap(lambda f: st.tuples(st.just(f[0]), st.sampled_from(f[1])))
    offset = st.integers(30 * DAY, 10 * YEAR) | st.integers(-10 * YEAR, -30 * DAY)
    return st.one_of(
        st.tuples(st.just("fields"), st.lists(one, min_size=1, max_size=3)),
        st.tuples(st.just("shift"), offset | st.sampled_from([200 * YEAR, -100 * YEAR])),
        st.tuples(st.just("bytes"), st.binary(max_size=64)),
    )


def draw(strategy: st.SearchStrategy, n: int) -> list[Any]:
    out: list[Any] = []

    @settings(
        max_examples=n,
        database=None,
        derandomize=True,
        deadline=None,
        phases=[Phase.generate],
        suppress_health_check=list(HealthCheck),
    )
    @given(strategy)
    def collect(x: Any) -> None:
        out.append(x)

    collect()
    return out


def apply(mutation: tuple[str, Any], template: msgspec.Struct) -> bytes:
    kind, what = mutation
    if kind == "bytes":
        return what
    d = msgspec.to_builtins(template)
    if kind == "shift":
        for name in d:
            if name.endswith("_ns") and isinstance(d[name], int):
                d[name] += what
    else:
        d.update(dict(what))
    return msgspec.msgpack.encode(d)


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


FUZZED = [t for t in TOPICS if t.pattern == "topic"]
CELLS = (CELL, "ecg", "twin")  # every hostile message goes to every service


def concrete(topic: Topic) -> str:
    return topic.suffix.replace("*", "fuzz")


async def test_hostile_messages_on_every_key_leave_every_service_serving_honest_input(
    tmp_path: Path, endpoint: str
) -> None:
    ecg = synthetic_ecg(100)
    n_hostile = len(chunks(ecg, 0)) * HOSTILE_PER_CHUNK
    drawn = draw(
        st.sampled_from(FUZZED).flatmap(lambda t: st.tuples(st.just(t), mutations(t.message))), n_hostile
    )
    plan = [drawn[i % len(drawn)] for i in range(n_hostile)]
    templates: dict[type, msgspec.Struct] = {type(m): m for m in SAMPLES}
    # A valid calibration is a command, not bad input (the ACL says who may send one): the fuzz sends the
    # decision maker's own calibration, broken, or again as it is (which changes nothing).
    own = Calibration(t_ns=0, seq=0, subject="config", rr_rest_s=0.85)
    templates[Calibration] = own
    cal_decoder = msgspec.msgpack.Decoder(Calibration)

    def harmless(topic: Topic, payload: bytes) -> bool:
        if topic.message is not Calibration:
            return True
        try:
            return same_calibration(cal_decoder.decode(payload), own)
        except (msgspec.ValidationError, msgspec.DecodeError):
            return True

    def honest_windows_from(base: int) -> list[HrvWindow]:
        return [
            HrvWindow(
                t_ns=base + (i + 1) * 30 * S,
                seq=i,
                start_ns=base + i * 30 * S,
                end_ns=base + (i + 1) * 30 * S,
                mean_rr_s=rr,
                n_beats=37,
                excluded_fraction=0.0,
                quality="good",
            )
            for i, rr in enumerate([0.85, 0.81, 0.75, 0.70, 0.62, 0.80, 0.85, 0.90, 0.84, 0.86])
        ]

    task_file = tmp_path / "shuttle.toml"
    task_file.write_text(TASK)

    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", endpoint)
        decider = InProcessService(
            "decision_maker",
            decision_main,
            DecisionSettings(rr_rest_s=0.85, republish_s=0.5),
            tmp_path / "d",
            endpoint,
        )
        # in a cell of its own: the decision maker's windows are the test's alone, so k can be checked
        analyser = InProcessService(
            "hrv_analyser", analyser_main, AnalyserSettings(), tmp_path / "a", endpoint, cell="ecg"
        )
        executor = InProcessService(
            "executor",
            executor_main,
            ExecutorSettings(task=str(task_file), fifo_priority=0, wait_for_signals=False),
            tmp_path / "x",
            endpoint,
            speed=SPEED,
        )
        twin = InProcessService(
            "operator_twin", twin_main, TwinSettings(), tmp_path / "t", endpoint, cell="twin"
        )
        await decider.listening(bus, "hrv/window", "operator/calibration")
        await analyser.listening(bus, "ecg/samples")
        await executor.listening(bus, "decision/selection", "operator/signal")
        twin_chunks = aiter(bus.subscribe("cadence/twin/ecg/samples", EcgChunk, maxsize=1))
        async with asyncio.timeout(20):
            await anext(twin_chunks)  # the twin is up
        wins = aiter(bus.subscribe("cadence/ecg/hrv/window", HrvWindow))
        sels = aiter(bus.subscribe(bus.key("decision/selection"), Selection, maxsize=10_000))
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport, maxsize=10_000))
        statuses = bus.subscribe("cadence/*/health/*", ServiceStatus, maxsize=10_000)
        async with asyncio.timeout(10):
            _, selection = await anext(sels)  # the decision maker's state: what valid copies repeat
        # the honest stream, stamped now that the cell is up (a loaded host can take many seconds to get
        # here): 100 s of ECG that have happened, nothing from the future, and not so old that an
        # analyser with no stream yet takes it for a stray from another time (far_from_clock)
        T0 = now_ns() - 100 * S
        honest_chunks = chunks(ecg, T0)
        # the decision maker's windows: near the clock, off the analyser's grid (T0 + 30 k)
        honest_windows = honest_windows_from(T0 - 290 * S)
        rss_before = rss_mb()

        sent: Counter[str] = Counter()
        got_k: list[int] = []

        async def answered(w: HrvWindow) -> int:
            nonlocal selection
            put(bus, bus.key("hrv/window"), w, block=True)
            async with asyncio.timeout(15):
                async for _, sel in sels:
                    if sel.window_end_ns == w.end_ns:
                        selection = sel
                        return sel.k
            raise AssertionError("unreachable")

        last_chunk, next_window = honest_chunks[0], 0
        for i, chunk in enumerate(honest_chunks):
            put(bus, "cadence/ecg/ecg/samples", chunk, block=True)
            last_chunk = chunk
            for topic, mutation in plan[i * HOSTILE_PER_CHUNK : (i + 1) * HOSTILE_PER_CHUNK]:
                if topic.message is EcgChunk:
                    template: msgspec.Struct = last_chunk
                elif topic.message is HrvWindow:
                    template = honest_windows[max(0, next_window - 1)]
                elif topic.message is Selection:
                    template = selection
                else:
                    template = templates[topic.message]
                payload = apply(mutation, template)
                if not harmless(topic, payload):
                    payload = b"\xc1" + payload
                for cell in CELLS:
                    bus.put_raw(f"cadence/{cell}/{concrete(topic)}", payload, block=True)
                sent[topic.suffix] += 1
            if i % 17 == 16 and next_window < len(honest_windows):
                got_k.append(await answered(honest_windows[next_window]))
                next_window += 1
            await asyncio.sleep(0)
        # hostile queries to the store, and honest ones after them
        weird = ["pareto/there/0", "pareto/there/99999999999999999999", "pareto/nope", "pareto/there/x/y"]
        replies = await asyncio.gather(*(bus.get(bus.key(k), ParetoSet, timeout=5) for k in weird))
        after, end_ns = rss_mb(), time.time_ns()

        honest_set = await bus.get(bus.key("pareto/there"), ParetoSet, timeout=5)
        reports, windows, last = [], [], {}
        async with asyncio.timeout(30):
            # the test's own hostile messages on these keys come back to it too: keep the services'
            async for _, r in cycles:
                if set(r.k_per_path) == {"there", "back"}:
                    reports.append(r)
                    if r.t_ns > end_ns:
                        break
            async for _, w in wins:  # the analyser's (the test's own hostile copies come back too)
                if 0 <= w.start_ns - T0 < DAY and (w.start_ns - T0) % (30 * S) == 0:
                    windows.append(w)
                    if len(windows) == 3:
                        break
            await anext(twin_chunks)
            async for _, st_ in statuses:  # one status of each service from after the fuzz
                if st_.t_ns > end_ns:
                    last[st_.service] = st_
                    if len(last) == 5:
                        break
        for svc in (twin, executor, analyser, decider, store):
            assert not svc.task.done(), "a service ended during the fuzz"
            await svc.close()

    print(
        f"\nfuzz: {sum(sent.values())} hostile messages to each of {len(CELLS)} cells, "
        f"RSS {rss_before:.0f} → {after:.0f} MB"
    )
    for suffix, n in sorted(sent.items()):
        print(f"  {suffix:22} {n:5}")
    for name, st_ in sorted(last.items()):
        dropped = {k: v for k, v in st_.counters.items() if k.startswith(("rejected/", "decode_errors"))}
        failures = sum(v for k, v in st_.counters.items() if k.startswith("handler_errors/"))
        print(f"  {name:15} failures {failures}  {dropped}")

    p, s, expected = Params.of(0.85), None, []
    s = State.initial(p)
    for w in honest_windows[: len(got_k)]:
        s = step(p, s, w.mean_rr_s).state
        expected.append(s.k)
    assert len(got_k) == len(honest_windows)
    assert got_k == expected
    assert [(w.start_ns - T0) // S for w in windows] == [0, 30, 60]
    assert all(w.quality == "good" and abs(w.mean_rr_s - 0.8) < 2e-3 for w in windows)
    # the robot ran only at what the decision maker decided (N = 15 clamped to the shuttle's 5)
    assert {k for r in reports for k in r.k_per_path.values()} <= {min(k, 5) for k in [8, *got_k]}
    assert all(r.message is None and r.error for rs in replies for r in rs)
    assert honest_set
    assert honest_set[0].message is not None
    assert set(last) == {"decision_maker", "hrv_analyser", "executor", "pareto_store", "operator_twin"}
    for st_ in last.values():
        assert not any(k.startswith("handler_errors/") for k in st_.counters), st_.counters
    assert last["decision_maker"].counters["decode_errors"] > 0
    assert last["hrv_analyser"].counters["decode_errors"] > 0
    assert after - rss_before < 300, "memory grew under the fuzz"
    assert set(sent) == {t.suffix for t in FUZZED}
    assert sum(sent.values()) == n_hostile
