"""`cadence top`: the graph, live. The aggregator counts rates, ages and what did not decode per key, and
says which service's status stopped coming; the command shows a running service's keys."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest
from rich.console import Console

from cadence.tools.top import Top
from schemas import HrvWindow, Selection, ServiceStatus
from schemas.topology import encode
from tests.support.cell import CELL


def render(top: Top, now: float, width: int = 250) -> str:
    console = Console(width=width, record=True)
    console.print(top.view(status_period_s=1.0, now=now))
    return console.export_text()


def test_rates_ages_bad_payloads_and_gone_services_are_counted() -> None:
    top = Top(CELL)
    sel = Selection(t_ns=1, seq=0, k=8, n=15, delta=0, reason="initial")
    for i in range(21):  # 2 Hz for 10 s
        top.on(f"cadence/{CELL}/decision/selection", encode(sel), now=100.0 + i * 0.5)
    top.on(f"cadence/{CELL}/decision/selection", b"\xc1 not msgpack", now=110.0)
    status = ServiceStatus(t_ns=1, seq=0, service="executor", state="moving", uptime_s=5.0, counters={
        "decode_errors": 2, f"rejected/cadence/{CELL}/decision/selection/stale": 1,
        f"handler_errors/cadence/{CELL}/operator/signal/ValueError": 4})  # fmt: skip
    top.on(f"cadence/{CELL}/health/executor", encode(status), now=101.0)
    k = top.keys[f"cadence/{CELL}/decision/selection"]
    assert (k.count, k.undecodable, k.type_name) == (22, 1, "decision.selection.v1")
    assert k.rate_hz(110.0) == pytest.approx(2.1, abs=0.15)
    text = render(top, now=110.0)
    assert "decision/selection" in text
    assert "decision_maker → executor" in text
    row = next(line for line in text.splitlines() if line.startswith("│ executor "))
    assert "gone 9 s" in row
    assert "moving" in row
    assert " 3 " in row
    assert " 4 " in row  # dropped 3, failed 4
    assert "no status" in next(line for line in text.splitlines() if line.startswith("│ pareto_store "))
    assert "executor → (tools)" in text  # health/executor: its own publisher


def test_the_operator_is_shown_with_their_movement_beside_rr_and_k() -> None:
    top = Top(CELL)
    assert "the operator" not in render(top, now=1.0)  # nothing read yet: nothing said
    win = HrvWindow(t_ns=30, seq=0, start_ns=0, end_ns=30, mean_rr_s=0.742, n_beats=40, excluded_fraction=0.0,
                    quality="good", movement_mg=251.0, moving_fraction=0.9)  # fmt: skip
    top.on(f"cadence/{CELL}/hrv/window", encode(win), now=1.0)
    top.on(f"cadence/{CELL}/decision/selection",
           encode(Selection(t_ns=30, seq=1, k=10, n=15, delta=0, reason="movement")), now=1.0)  # fmt: skip
    row = render(top, now=2.0).split("the operator")[1].splitlines()[4]
    assert all(part in row for part in ("0.742 s", "good", "251 mg", "90%", "10 of 15", "movement")), row
    top.on(f"cadence/{CELL}/hrv/window", encode(msgspec.structs.replace(win, movement_mg=None)), now=3.0)
    assert "no accelerometer" in render(top, now=3.0)


@pytest.mark.asyncio
async def test_cadence_top_shows_a_running_services_keys(tmp_path: Path, endpoint: str) -> None:
    from common.runtime.bus import Bus, BusConfig
    from services.decision_maker.__main__ import Settings, main
    from tests.support.cell import InProcessService

    async with await Bus.open(BusConfig(listen=[endpoint]), CELL):
        svc = InProcessService(
            "decision_maker", main, Settings(republish_s=0.1, rr_rest_s=0.9), tmp_path, endpoint
        )
        # the service reports every 0.1 s; top is told 1 s, so a status late by a loaded machine's
        # stall (up to 3 s) still counts as alive
        argv = ["top", "--connect", endpoint, "--once", "3", "--status-period", "1"]
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cadence", *argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            env={**os.environ, "COLUMNS": "250"},
        )  # fmt: skip
        out, err = await asyncio.wait_for(proc.communicate(), 120)
        svc.stop.set()
        await svc.task
    text = out.decode()
    assert proc.returncode == 0, err.decode()
    assert "decision/selection" in text
    assert "decision.selection.v1" in text
    assert "health/decision_maker" in text
    row = next(line for line in text.splitlines() if "decision_maker" in line and "yes" in line)
    assert "running" in row


def test_every_key_is_shown_whole_on_a_terminal_of_80_columns() -> None:
    """At 80 columns every key was cut ("operator/s…" for operator/separation and operator/signal)."""
    top = Top(CELL)
    sel = Selection(t_ns=1, seq=0, k=8, n=15, delta=0, reason="initial")
    for key in ("operator/separation", "operator/signal", "decision/selection", "robot/state"):
        top.on(f"cadence/{CELL}/{key}", encode(sel), now=100.0)
    text = render(top, now=101.0, width=80)
    for key in ("operator/separation", "operator/signal", "decision/selection", "robot/state"):
        assert f"│ {key} " in text, text
