"""`cadence plant` (issue 58): every cell on the mesh in one table. The aggregator keeps each cell's
statuses, robot, selection and window with their ages, and says which service of which cell went quiet;
the command reads two cells on one bus."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys

import pytest
from rich.console import Console

from cadence.tools.plant import Plant, plant_watch
from common.runtime.bus import Bus, BusConfig
from schemas import HrvWindow, RobotState, Selection, ServiceStatus
from schemas.topology import SERVICES, encode
from tests.support.cell import free_port, put


def render(plant: Plant, now: float) -> str:
    console = Console(width=250, record=True)
    console.print(plant.view(status_period_s=1.0, now=now))
    return console.export_text()


def status(service: str, state: str = "serving") -> ServiceStatus:
    return ServiceStatus(t_ns=1, seq=0, service=service, state=state, uptime_s=5.0, counters={})


def test_each_cell_is_a_row_with_its_services_robot_k_window_and_their_ages() -> None:
    plant = Plant()
    for s in SERVICES:
        if s != "ecg_gateway":  # the twin is this cell's ECG source
            plant.on(f"cadence/line1-a/health/{s}", encode(status(s)), now=100.0)
    plant.on("cadence/line1-a/health/executor", encode(status("executor", "holding")), now=100.5)
    robot = RobotState(t_ns=1, seq=0, q=[0.0] * 6, qd=[0.0] * 6, tcp=[0.0] * 6, state="stopped",
                       reason="protective stop: a bump")  # fmt: skip
    plant.on("cadence/line1-a/robot/state", encode(robot), now=100.8)
    sel = Selection(t_ns=1, seq=0, k=6, n=15, delta=-1, reason="stress")
    plant.on("cadence/line1-a/decision/selection", encode(sel), now=99.0)
    window = HrvWindow(t_ns=2, seq=0, start_ns=0, end_ns=2, mean_rr_s=0.812, n_beats=30,
                       excluded_fraction=0.0, quality="good")  # fmt: skip
    plant.on("cadence/line1-a/hrv/window", encode(window), now=98.0)
    plant.on("cadence/line1-b/health/executor", encode(status("executor")), now=90.0)  # quiet since
    plant.on("cadence/line1-b/hrv/window", b"\xc1 not msgpack", now=100.0)  # ignored, not a crash
    text = render(plant, now=101.0)
    a = next(line for line in text.splitlines() if line.startswith("│ line1-a "))
    b = next(line for line in text.splitlines() if line.startswith("│ line1-b "))
    assert "5 of 5 up" in a and "executor: holding" in a
    assert "stopped: protective stop: a bump" in a
    assert "6 of 15 (stress)" in a
    assert "0.812 s" in a
    assert "0.2 / 2.0 / 3.0" in a  # robot, k, window: seconds since each came
    assert "0 of 5 up" in b and "gone: executor" in b
    assert "no cell seen yet" in render(Plant(), now=0.0)


@pytest.mark.asyncio
async def test_cadence_plant_shows_two_cells_on_one_bus() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    async with await Bus.open(BusConfig(listen=[endpoint]), "pc1") as bus:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cadence", "plant", "--connect", endpoint, "--once", "20",
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "COLUMNS": "200"},
        )  # fmt: skip
        try:
            for key in plant_watch():  # every cell's keys: one concrete key is enough to know it listens
                await bus.until_subscribed(key.replace("*", "pc2", 1).replace("*", "executor"), 60)
            for cell in ("pc1", "pc2"):
                put(bus, f"cadence/{cell}/health/executor", status("executor"), block=True)
                sel = Selection(t_ns=1, seq=0, k=4 if cell == "pc1" else 9, n=15, delta=0, reason="initial")
                put(bus, f"cadence/{cell}/decision/selection", sel, block=True)
            out, err = await asyncio.wait_for(proc.communicate(), 90)
        finally:
            if proc.returncode is None:
                proc.kill()
    text = out.decode()
    assert proc.returncode == 0, err.decode()
    assert "2 cells" in text
    assert "4 of 15 (initial)" in text and "9 of 15 (initial)" in text
