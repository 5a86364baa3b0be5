"""A full disk is a state, not a crash (issue 44; DESIGN §9): on a small tmpfs filled while a service runs,
the executor holds the arm still and goes on by itself when space returns, the decision maker still
decides and publishes, and the demo keeps its summary elsewhere. Needs a tmpfs mount (root with
CAP_SYS_ADMIN); skipped, with the reason, where mounting is not allowed."""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from rich.console import Console

from cadence.demo.summary import keep_summary
from common.trajectory.task import load_task
from schemas import CycleReport, OperatorSignal, RobotEvent, RobotState, Selection, ServiceStatus
from schemas.topology import encode
from services.decision_maker.__main__ import Settings as DecisionSettings
from services.decision_maker.__main__ import main as decision_main
from services.decision_maker.state import STATE_FILE
from services.executor.__main__ import main as executor_main
from tests.support.cell import CELL, Cell, put, status_of
from tests.support.decisions import answer, window
from tests.support.executor import TASK, cached_sets, next_of, sim_settings, store_serving


class Disk:
    """A 2 MB tmpfs: ``fill()`` takes every byte left, ``free()`` gives it back."""

    def __init__(self, path: Path) -> None:
        self.path, self.filler = path, path / ".filler"

    def fill(self) -> None:
        with contextlib.suppress(OSError), self.filler.open("ab") as f:
            while True:
                f.write(b"\0" * 65536)
                f.flush()

    def free(self) -> None:
        self.filler.unlink(missing_ok=True)


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Disk]:
    mount = tmp_path / "small"
    mount.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount)], capture_output=True,
                       text=True, check=False)  # fmt: skip
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({r.stderr.strip() or r.returncode}): needs root")
    try:
        yield Disk(mount)
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


@pytest.fixture
def task_file(tmp_path: Path) -> Path:
    p = tmp_path / "shuttle.toml"
    p.write_text(TASK)
    return p


# The disk fills while no write is in flight: before the start, or while the arm waits, in lockstep (where
# the executor's writes run at once, in the loop's thread). Filled beside a write in a worker thread, the
# page that write's rename freed let every later write through: no refusal, and the test timed out (CI).
@pytest.mark.lockstep
@pytest.mark.asyncio
async def test_the_executor_holds_the_arm_on_a_full_disk_and_goes_on_by_itself_when_space_returns(
    task_file: Path, tmp_path: Path, cell: Cell, disk: Disk
) -> None:
    """Before: 14 restarts in 220 s, each dying on ENOSPC with a traceback, no cycle for 276 s."""
    data = disk.path / "ex"
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        await cached_sets(bus, task_file, data)
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        disk.fill()  # the cycle's record is the first thing it writes
        ex = cell.service("executor", executor_main, sim_settings(task_file), data)
        try:
            said = await next_of(events, lambda e: e.kind == "started")
            refused = await next_of(events, lambda e: e.kind == "refused" and "cannot write" in e.message)
            held = await next_of(states, lambda s: s.state == "refused" and "No space left" in s.reason)
            still = [await next_of(states) for _ in range(20)]  # a while: held, not moving, not restarted
            assert all(s.state != "moving" for s in still)
            assert not ex.task.done()
            disk.free()
            back = await next_of(events, lambda e: e.kind == "info" and "written again" in e.message, 10)
            await next_of(states, lambda s: s.state == "moving", timeout=10)
            report = await next_of(cycles, timeout=60)
            await asyncio.wait_for(ex.task, 15)
        finally:
            await store.close()
    assert "No space left on device" in refused.message
    assert "holding the arm still" in refused.message
    assert "executor_state.json" in refused.message
    assert said.kind == "started"
    assert held.path_id is None
    assert back is not None
    assert report.cycle == 0
    assert ex.ctx.counters["write_errors"] == 1  # said once, however long it lasted


@pytest.mark.lockstep
@pytest.mark.asyncio
async def test_a_hold_for_a_full_disk_is_said_when_the_disk_first_refused_a_write_the_arm_did_not_wait_for(
    task_file: Path, tmp_path: Path, cell: Cell, disk: Disk
) -> None:
    """A selection received while the arm waits is written without holding the arm (on a full disk: "going
    on without it"); the next path's record is one the arm waits for. Before: the hold went unsaid."""
    async with cell.session() as bus:
        store = await store_serving(bus, task_file, tmp_path / "store", cell)
        states = aiter(bus.subscribe(bus.key("robot/state"), RobotState, maxsize=10_000))
        events = aiter(bus.subscribe(bus.key("robot/event"), RobotEvent, maxsize=1000))
        cycles = aiter(bus.subscribe(bus.key("robot/cycle"), CycleReport))
        settings = sim_settings(task_file, wait_for_signals=True)
        ex = cell.service("executor", executor_main, settings, disk.path / "ex")
        try:
            await next_of(states, lambda s: s.mode == "waiting")  # at "there", for the part
            disk.fill()
            sel = Selection(t_ns=cell.now_ns(), seq=1, k=5, n=5, delta=2, reason="rest", window_end_ns=1)
            put(bus, bus.key("decision/selection"), sel, block=True)
            going_on = await next_of(events, lambda e: "cannot write" in e.message)
            put(bus, bus.key("operator/signal"), OperatorSignal(t_ns=cell.now_ns(), seq=0, name="part"),
                block=True)  # fmt: skip
            refused = await next_of(events, lambda e: e.kind == "refused")
            held = await next_of(states, lambda s: s.state == "refused")
            disk.free()
            await next_of(events, lambda e: "written again" in e.message, 10)
            report = await next_of(cycles, timeout=60)
            await asyncio.wait_for(ex.task, 15)
        finally:
            await store.close()
    assert going_on.kind == "info"
    assert "going on without it" in going_on.message
    assert "No space left on device" in refused.message
    assert "holding the arm still" in refused.message
    assert "No space left" in held.reason
    assert report.k_per_path == {"there": 3, "back": 5}  # held before "back", not skipped
    assert ex.ctx.counters["write_errors"] == 1  # one refusal of the disk, the hold said apart


@pytest.mark.asyncio
async def test_the_decision_maker_decides_and_publishes_on_a_full_disk_and_says_k_is_not_persisted(
    tmp_path: Path, cell: Cell, disk: Disk
) -> None:
    """Before: it persisted before it published, so windows got no selection while the old k was
    republished, and k jumped when space came back."""
    windows = [window(i, rr) for i, rr in enumerate([0.85, 0.80, 0.74, 0.69, 0.66, 0.80])]
    settings = DecisionSettings(rr_rest_s=0.85, republish_s=0.2)
    async with cell.session() as bus:
        svc = cell.service("decision_maker", decision_main, settings, disk.path)
        await svc.listening(bus, "hrv/window")
        sels = aiter(bus.subscribe(bus.key("decision/selection"), Selection))

        ks = [(await answer(bus, sels, windows[0])).k]
        disk.fill()
        ks += [(await answer(bus, sels, w)).k for w in windows[1:4]]
        full: ServiceStatus = await status_of(bus, "decision_maker", lambda s: "cannot write" in s.detail)
        disk.free()
        ks += [(await answer(bus, sels, w)).k for w in windows[4:]]
        ok: ServiceStatus = await status_of(bus, "decision_maker", lambda s: s.detail == "")
        await svc.close()
    assert len(set(ks[:4])) > 1  # k moved while nothing could be written
    assert "No space left on device" in full.detail
    assert "deciding from memory" in full.detail
    assert full.counters["unpersisted"] >= 3
    assert ok.state
    assert json.loads((disk.path / STATE_FILE).read_text())["k"] == ks[-1]


def test_the_demos_summary_goes_elsewhere_with_one_line_when_its_folder_is_full(disk: Disk) -> None:
    disk.fill()
    console = Console(record=True, width=200)
    where = keep_summary(disk.path, b'{"cycles": 3}', console)
    said = console.export_text()
    assert where.parent != disk.path
    assert json.loads(where.read_text()) == {"cycles": 3}
    assert said.count("\n") == 1
    assert f"{disk.path}: cannot write summary.json" in said
    assert str(where) in said


@pytest.mark.asyncio
async def test_the_demos_supervisor_never_starts_a_service_once_stopping_has_begun(tmp_path: Path) -> None:
    """A service that died half a second before the end was started again after the stop had passed it,
    and the demo hung until killed."""
    from cadence.demo.supervise import Supervised

    stopping = asyncio.Event()
    died = asyncio.Event()
    sup = Supervised("no_such_service", {}, tmp_path / "log")  # python -m exits 1 at once

    def on_restart(name: str, rc: int) -> None:
        died.set()
        stopping.set()  # the end comes within the restart's delay

    started = time.monotonic()
    await asyncio.wait_for(sup.supervise(stopping, on_restart), 10)
    assert died.is_set()
    assert sup.restarts == 1
    assert sup.proc is not None
    assert sup.proc.returncode == 1
    assert time.monotonic() - started < 5


def test_a_full_disk_is_not_taken_for_a_damaged_store(disk: Disk, example_sets: Path) -> None:
    """Before: SetStore.open moved the healthy database aside as corrupt ("database or disk is full" is
    SQLite's DatabaseError too), left a 0-byte pareto.sqlite, and raised."""
    import shutil

    from services.pareto_store.store import SetStore
    from tests.support.paths import EXAMPLE_TASK

    db = disk.path / "pareto.sqlite"
    shutil.copy(example_sets, db)
    size = db.stat().st_size
    disk.fill()
    store, problem = SetStore.open(db)
    try:
        _, sets = store.current(load_task(EXAMPLE_TASK))
    finally:
        store.close()
    assert problem is None or "not damaged, left as it is" in problem
    assert len(sets) == 6
    assert db.stat().st_size == size
    assert not list(disk.path.glob("*.corrupt-*"))


def test_a_recording_on_a_filling_disk_ends_with_one_line_and_stays_readable(disk: Disk) -> None:
    """`cadence record` on a filling disk kept "recording" for 20 s writing nothing, then left an
    unreadable 16 KB file: it ends at the first write the disk refuses, says so, and what reached the
    disk before is read as far as it goes."""
    from cadence.tools.recording import Recorder, read

    path = disk.path / "run.mcap"
    rec = Recorder(path)
    for i in range(200):
        rec.write(f"cadence/{CELL}/decision/selection", encode(Selection(t_ns=i + 1, seq=i, k=3, n=15,
                  delta=0, reason="hold")), log_time_ns=i + 1)  # fmt: skip
    rec.flush()
    disk.fill()
    payload = encode(
        ServiceStatus(t_ns=1, seq=0, service="x" * 60, state="y" * 4000, uptime_s=1.0, counters={})
    )
    for i in range(2000):  # much more than is left: the disk refuses a flush
        rec.write(f"cadence/{CELL}/health/x", payload, log_time_ns=1000 + i)
        if i % 100 == 99:
            rec.flush()
        if rec.failed:
            break
    rec.close()  # no exception: what could not be written is said in failed
    assert rec.failed is not None
    assert f"cannot write {path}: No space left on device" in rec.failed
    disk.free()
    notes: list[str] = []
    every = list(read(path, notes=notes))
    kept = [m for m in every if m.key.endswith("selection")]
    assert len(kept) == 200
    # what it says is in the file is what is (once it said the messages it had been handed, 2,605 for 2,482)
    assert rec.on_disk == len(every) < rec.count
    assert notes
    assert "ends without its footer" in notes[0]


def test_a_recording_whose_disk_refuses_the_close_says_so_with_what_is_readable() -> None:
    """`cadence record` on a disk that filled at the close printed "4522 messages written", exited 0, and
    left a file with no footer: what the file object still held went to the disk in its close, whose
    refusal was swallowed. The footer and that tail are now flushed and synced inside the close's guard.
    /dev/full refuses every write that reaches it, as a disk full by the close does: a few messages stay
    in the writer's and the file's buffers until then."""
    from cadence.tools.recording import Recorder

    rec = Recorder(Path("/dev/full"))
    for i in range(20):
        rec.write(f"cadence/{CELL}/decision/selection", encode(Selection(t_ns=i + 1, seq=i, k=3, n=15,
                  delta=0, reason="hold")), log_time_ns=i + 1)  # fmt: skip
    assert rec.failed is None  # nothing reached the disk yet
    rec.close()
    assert rec.failed is not None and "No space left on device" in rec.failed
    assert rec.on_disk == 0 < rec.count == 20  # nothing readable: said, not "20 written"


def test_a_report_onto_a_full_disk_is_one_line_naming_the_folder(disk: Disk, tmp_path: Path) -> None:
    from tests.support.sessions import write_run

    run = write_run(tmp_path)
    disk.fill()
    r = subprocess.run([sys.executable, "-m", "cadence", "report", str(run), "--out", str(disk.path / "rep")],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1, r.stderr
    assert "the report cannot be written there (No space left on device)" in r.stderr


def test_a_study_plan_on_a_full_disk_leaves_no_empty_sheet_and_a_rerun_writes_it(disk: Disk) -> None:
    """`cadence study plan` on a full disk left demographics.csv at 0 bytes, never written later."""
    plan = disk.path / "plan.toml"
    disk.fill()
    cmd = [sys.executable, "-m", "cadence", "study", "plan", "--subjects", "6", "--out", str(plan)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "cannot be written (No space left on device)" in r.stderr
    assert r.stderr.count("\n") == 1
    assert not (disk.path / "demographics.csv").exists()
    assert not plan.exists()
    disk.free()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert (disk.path / "demographics.csv").read_text().count("\n") == 7  # a header and 6 subjects


def test_a_study_plan_on_an_almost_full_disk_names_the_file_that_failed_leaving_neither(disk: Disk) -> None:
    """Room for one small file and not two (issue 56): the plan was written, the sheet failed under the
    plan's name, and a rerun was refused because the plan existed, so the sheet was never written. Now the
    error names the file that failed, neither is left, and a rerun once there is room writes both."""
    plan = disk.path / "plan.toml"
    disk.fill()
    disk.filler.write_bytes(disk.filler.read_bytes()[:-4096])  # one page back: one small file's room
    cmd = [sys.executable, "-m", "cadence", "study", "plan", "--subjects", "6", "--out", str(plan)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.count("\n") == 1, r.stderr
    assert "cannot be written (No space left on device)" in r.stderr
    assert not plan.exists() and not (disk.path / "demographics.csv").exists()
    failed = r.stderr.split(": cannot be written")[0].split()[-1]
    assert failed == str(plan), r.stderr  # the sheet took the page; the plan, written second, failed
    disk.free()
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert plan.exists() and (disk.path / "demographics.csv").read_text().count("\n") == 7
