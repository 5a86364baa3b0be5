"""What every service shares: strict config with environment overrides, and systemd notification."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from common.runtime.bus import BusConfig
from common.runtime.config import CommonSettings, read_config, section
from common.runtime.errors import ConfigError
from common.runtime.service import sd_notify, watchdog_period_s
from tests.support.cell import CELL


def test_environment_variables_override_the_file(tmp_path: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text('[bus]\nmode = "client"\nconnect = ["tcp/10.0.0.1:7447"]\n[cadence]\ncell = "cellA"\n')
    raw = read_config(str(cfg))
    env = {"CADENCE_BUS_CONNECT": '["tcp/127.0.0.1:7447"]', "CADENCE_CADENCE_STATUS_PERIOD_S": "0.5"}
    bus = section(raw, "bus", BusConfig, str(cfg), env)
    common = section(raw, "cadence", CommonSettings, str(cfg), env)
    assert bus.mode == "client"
    assert bus.connect == ["tcp/127.0.0.1:7447"]
    assert common.cell == "cellA"
    assert common.status_period_s == 0.5


def test_an_unknown_key_names_the_file_and_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"c\.toml: \[bus\] .*listen_on"):
        section({"bus": {"listen_on": []}}, "bus", BusConfig, "c.toml", {})


def test_a_bad_environment_value_names_the_variable() -> None:
    with pytest.raises(ConfigError, match="CADENCE_BUS_LEASE_MS: \\[bus\\] lease_ms"):
        section({}, "bus", BusConfig, "c.toml", {"CADENCE_BUS_LEASE_MS": "soon"})


def test_a_misspelled_environment_variable_is_named_not_the_defaults() -> None:
    """An unknown key from the environment was reported as "<defaults>: … unknown field" (issue 28)."""
    with pytest.raises(ConfigError, match=r"^CADENCE_BUS_CONECT: \[bus\] conect: .*unknown field"):
        section({}, "bus", BusConfig, "<defaults>", {"CADENCE_BUS_CONECT": "['tcp/127.0.0.1:7447']"})
    with pytest.raises(ConfigError, match=r"^c\.toml: \[bus\] listen_on"):  # one from the file names the file
        section({"bus": {"listen_on": []}}, "bus", BusConfig, "c.toml", {})


def test_a_missing_config_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.toml"):
        read_config(str(tmp_path / "nope.toml"))


def test_sd_notify_sends_a_datagram_to_the_notify_socket(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)
        server.settimeout(5)
        assert sd_notify("READY=1", {"NOTIFY_SOCKET": path})
        assert server.recv(64) == b"READY=1"
    assert not sd_notify("READY=1", {})


def test_the_watchdog_pings_at_half_its_period() -> None:
    assert watchdog_period_s({"WATCHDOG_USEC": "4000000"}) == 2.0
    assert watchdog_period_s({}) is None
    assert watchdog_period_s({"WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"}) is None


@pytest.mark.asyncio
async def test_a_service_that_reaches_no_router_and_no_peer_says_so_in_its_status(tmp_path: Path) -> None:
    """Zenoh says nothing when a session's endpoints are all unreachable: the service does, in its log
    and its status, within a few seconds."""
    import asyncio

    from services.decision_maker.__main__ import Settings, main
    from tests.support.cell import InProcessService, free_port

    nowhere = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    svc = InProcessService("decision_maker", main, Settings(), tmp_path, nowhere)
    async with asyncio.timeout(20):
        while svc.ctx is None or not svc.ctx.link:
            await asyncio.sleep(0.1)
    assert svc.ctx.link == f"connected to no router and no peer (connect: {nowhere})"
    assert svc.ctx.status(0).detail.startswith("connected to no router and no peer")
    svc.stop.set()
    await svc.task


@pytest.mark.asyncio
async def test_a_services_status_is_stamped_on_data_time_as_every_other_key() -> None:
    """health/* once carried the wall's time while every other key carried data time: in a run at 100× a
    recording put each status far behind the windows and selections it stood beside."""
    import time

    from common.runtime.memory import MemoryNetwork
    from common.runtime.service import ServiceContext

    epoch = time.time_ns() - 10 * 1_000_000_000  # the run began 10 s of the wall ago: 1,000 s of data
    common = CommonSettings(speed=100.0, epoch_ns=epoch)
    ctx = ServiceContext("decision_maker", MemoryNetwork().bus(role="decision_maker"), common, None, None)
    before = common.clock.now_ns()
    stamped = ctx.status(0).t_ns
    assert before <= stamped <= common.clock.now_ns()
    assert stamped - epoch > 900 * 1_000_000_000  # data time, not the wall's 10 s


def test_cadence_get_alone_on_the_bus_says_why_no_reply_came() -> None:
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "cadence", "get", f"cadence/{CELL}/decision/selection", "--timeout", "1"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1, r.stderr
    assert "connected to no router and no peer" in r.stderr, r.stderr


@pytest.mark.parametrize(
    "argv",
    [["-m"], ["/opt/cadence/.venv/bin/cadence", "run", "hrv_analyser"]],
    ids=["python -m services.NAME", "cadence run NAME"],
)
def test_a_sigterm_while_a_service_is_still_importing_is_a_clean_exit(argv: list[str]) -> None:
    """A supervisor's stop that comes during a service's imports (a restart the cell is stopped during, on
    a loaded host): exit 0, not death by the signal (systemd's ExecMainStatus 15, issue 53). The process
    takes its first package as a service start would, then is stopped before anything else it imports;
    a plain script that imports the same package is not touched."""
    code = (
        "import os, signal, sys; sys.argv = {argv!r}; import {pkg}; "
        "os.kill(os.getpid(), signal.SIGTERM); import numpy; sys.exit(3)"
    )
    pkg = "services" if argv == ["-m"] else "cadence"
    r = subprocess.run([sys.executable, "-c", code.format(argv=argv, pkg=pkg)], timeout=60)
    assert r.returncode == 0
    r = subprocess.run([sys.executable, "-c", code.format(argv=["tool.py"], pkg=pkg)], timeout=60)
    assert r.returncode == -signal.SIGTERM
