"""Every service's `__main__` as a process: it comes up, reports its status, and exits 0 on SIGTERM (and
SIGHUP)."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cadence.cli import SERVICES
from common.runtime.bus import Bus, BusConfig
from schemas import ServiceStatus
from tests.support.cell import CELL

pytestmark = pytest.mark.asyncio


CASES = [
    (name, signal.SIGTERM) for name in sorted(set(SERVICES) - {"ur_emulator"})
]  # the emulator: its tests
CASES.append(("decision_maker", signal.SIGHUP))  # a closed terminal or `kill -HUP` stops it cleanly too


@pytest.mark.parametrize(("name", "sig"), CASES, ids=[f"{n}-{s.name}" for n, s in CASES])
async def test_the_service_starts_reports_and_stops_on_sigterm(
    name: str, sig: signal.Signals, tmp_path: Path, endpoint: str
) -> None:
    cfg = tmp_path / "c.toml"
    text = f"[cadence]\ndata_dir = '{tmp_path}'\nstatus_period_s = 0.1\n[bus]\nconnect = ['{endpoint}']\n"
    if name == "ecg_gateway":  # a replay of a small synthetic recording (time s, µV)
        csv = tmp_path / "ecg.csv"
        t = np.arange(0, 60, 1 / 130)
        np.savetxt(csv, np.c_[t, 1000 * np.exp(-(((t % 0.8) - 0.4) ** 2) / 2e-4)], delimiter=",")
        text += f"[ecg_gateway]\nrecord = '{csv}'\n"
    cfg.write_text(text)
    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        health = aiter(bus.subscribe(bus.key(f"health/{name}"), ServiceStatus, maxsize=1))
        proc = subprocess.Popen([sys.executable, "-m", f"services.{name}", "--config", str(cfg)])
        try:
            async with asyncio.timeout(30):
                _, status = await anext(health)
            assert status.service == name
            proc.send_signal(sig)
            assert await asyncio.to_thread(proc.wait, 20) == 0
        finally:
            proc.kill()
