"""`cadence bench plant` (issue 58): N cells as deployed (each its own router and CA, its services'
accounts; the first a real one, the rest synthetic), behind line routers and the plant's, read by the
plant monitor and `cadence record --plant`. The benchmark prints its figures; this asserts what must hold
on any host, loaded or not: every cell seen by the plant, nothing the plant keeps lost, the in-cell
traffic delivered, the timed keys timed in both phases, and the host's own delay in waking a thread beside
them. The timings themselves are figures (docs/operations.md), not assertions."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from cadence.bench.plant_cells import PROFILE
from cadence.deploy.cell import publishers
from schemas.topology import topic_of
from tests.support.paths import BENCH_QUICK

pytestmark = pytest.mark.bench
CELLS = 20 if BENCH_QUICK else 50


def test_every_key_of_the_profile_is_put_by_an_account_the_cells_router_lets_put_it() -> None:
    """A key put by an account the graph does not name its publisher would be dropped by the router:
    the profile would measure less than a cell sends."""
    for stream in PROFILE:
        topic = topic_of(f"cadence/c1/{stream.suffix}")
        assert topic is not None, stream.suffix
        mine = stream.suffix == f"health/{stream.account}"
        assert mine or stream.account in publishers(topic), stream


def test_bench_plant_reads_every_cell_and_loses_nothing_it_keeps() -> None:
    seconds, rounds = ("3", "1") if BENCH_QUICK else ("20", "3")
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "bench", "plant", "--cells", str(CELLS), "--seconds", seconds,
         "--rounds", rounds],
        capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    print(r.stdout)
    assert r.returncode == 0, r.stderr[-3000:]
    (f,) = json.loads(r.stdout.strip().splitlines()[-1])
    assert f["cells"] == CELLS and f["cells_seen"] == CELLS
    assert f["lines"] == -(-CELLS // 10)
    assert f["derived_put"] >= CELLS  # the cells put windows, cycles and events while the plant read
    assert f["derived_lost"] == {"monitor": 0, "recorder": 0}
    assert f["lost_puts"] == 0
    assert f["rounds"] == int(rounds)
    assert f["real_cell"] == "line1-cell1"  # a real cell among them: its services, its own figures
    for phase in ("alone", "watched", "real_alone", "real_watched"):
        for key, (p50, p99) in f[phase]["latency_ms"].items():
            assert 0 < p50 <= p99, (phase, key)
            assert len(f[phase]["p99_by_phase"][key]) == int(rounds)
    for phase in ("alone", "watched"):  # the host's own delay, timed in the same phases
        assert set(f[phase]["latency_ms"]) == {"robot/state", "operator/separation", "host wake"}
    assert f["delivered"]["operator/separation"] > 0.99  # put with QoS drop, as the sensor's adapter does
    assert f["recorded_bytes_per_cell_day"] > 0
