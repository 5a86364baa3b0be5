"""`cadence bench store`: the Pareto store's answers while it plans and once the sets are stored."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.trajectory.task import load_task
from schemas.topology import DEFAULT_CELL


@dataclass(frozen=True, slots=True)
class StoreBench:
    during_planning_ms: list[float]
    stored_ms: list[float]

    @staticmethod
    def pct(values: list[float], q: float) -> float:
        return float(np.percentile(values, q)) if values else float("nan")


async def bench_store(task_path: str, queries: int = 200) -> StoreBench:
    """Query latency on loopback against a store process: while it plans, and for a stored set."""
    import asyncio
    import socket
    import subprocess
    import sys
    import tempfile

    from common.runtime.bus import Bus, BusConfig
    from schemas.health import ServiceStatus
    from schemas.topology import AnyMessage

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    task = load_task(task_path)
    first = next(iter(task.paths))
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "c.toml"
        cfg.write_text(
            f"[cadence]\ndata_dir = '{tmp}'\nstatus_period_s = 0.05\n[bus]\nconnect = ['{endpoint}']\n"
            f"[pareto_store]\ntask = '{Path(task_path).resolve()}'\nshipped_sets = false\n"  # it plans
        )
        client = await Bus.open(BusConfig(listen=[endpoint]), DEFAULT_CELL)
        async with client:
            status = client.subscribe(client.key("health/pareto_store"), ServiceStatus, maxsize=1)
            proc = subprocess.Popen([sys.executable, "-m", "services.pareto_store", "--config", str(cfg)])
            try:
                latest: list[str] = [""]

                async def watch() -> None:
                    async for _, st in status:
                        latest[0] = st.state

                watcher = asyncio.create_task(watch())
                during: list[float] = []
                key = client.key(f"pareto/{first}")
                async with asyncio.timeout(300):
                    while latest[0] != "serving":
                        t0 = time.perf_counter()
                        replies = await client.get(key, AnyMessage, timeout=5.0)
                        if replies and latest[0].startswith("planning"):
                            during.append((time.perf_counter() - t0) * 1e3)
                stored = []
                for _ in range(queries):
                    t0 = time.perf_counter()
                    replies = await client.get(key, AnyMessage, timeout=5.0)
                    if not replies or replies[0].message is None:
                        raise RuntimeError(f"no stored set for {first}")
                    stored.append((time.perf_counter() - t0) * 1e3)
                watcher.cancel()
            finally:
                proc.terminate()
                proc.wait(timeout=20)
    return StoreBench(during, stored)
