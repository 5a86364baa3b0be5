"""The shipped deployment under a real systemd (issue 16): systemd 252 boots as PID 1 of a new PID and
mount namespace, with private /tmp, /var/tmp and /run (its tmpfiles would empty the machine's) and
a private /etc and overlays on /var/lib, /var/log and /opt: the install touches nothing real. In there,
``cadence install`` with the twin and the sim arm, then ``systemctl start cadence.target``, and the
cell is watched from outside over its router, as the monitor account: loop closed, restarts after
kill -9 and kill -STOP, ACL and mTLS hold, clean stop, JSON in the journal, uninstall. The figures are
printed (pytest -s) for the note."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from common.runtime.bus import Bus, BusConfig
from common.trajectory.task import load_task
from schemas import CycleReport, HrvWindow, Selection
from tests.support.cell import CELL, free_port, put
from tests.support.paths import EXAMPLE_TASK, REPO

TOOLS = ("unshare", "nsenter", "systemctl", "uv")
SYSTEMD = Path("/lib/systemd/systemd")
needs_root = pytest.mark.skipif(
    os.geteuid() != 0 or not SYSTEMD.exists() or any(shutil.which(t) is None for t in TOOLS),
    reason="needs root, systemd, unshare, nsenter and uv: it boots systemd in a namespace (CI runs as root)",
)

BOOT = r"""#!/bin/bash
# inside unshare --fork --pid --mount --mount-proc: make the machine's state private, then boot
set -euo pipefail
STAGE=$1; SRC=$2
mount --make-rprivate /
mount -t tmpfs tmpfs "$STAGE/ov"
# /etc is copied (small), not overlaid: overlayfs gave ESTALE on unlinking files that sandboxed units
# had read, which `cadence uninstall` must do
mkdir -p "$STAGE/ov/etc"; cp -a /etc/. "$STAGE/ov/etc/"; mount --bind "$STAGE/ov/etc" /etc
for d in var/lib var/log opt; do
  n=${d//\//_}; mkdir -p "$STAGE/ov/$n/u" "$STAGE/ov/$n/w"
  mount -t overlay overlay -o "lowerdir=/$d,upperdir=$STAGE/ov/$n/u,workdir=$STAGE/ov/$n/w" "/$d"
done
mount --bind "$SRC" "$STAGE/src"        # the checkout may be under /tmp: keep it where it was
mount -t tmpfs tmpfs /tmp
mount -t tmpfs tmpfs /var/tmp
mount -t tmpfs -o mode=755 tmpfs /run  # its own runtime state and volatile journal
mkdir -p "$SRC"; mount --bind "$STAGE/src" "$SRC"
mkdir -p /etc/systemd/system
cat > /etc/systemd/system/cadence-test-boot.target <<EOT
[Unit]
Description=A minimal boot for Cadence's systemd test
Requires=systemd-journald.socket
After=systemd-journald.socket
AllowIsolate=yes
EOT
exec /lib/systemd/systemd --system --unit=cadence-test-boot.target
"""

UNITS = ["router", "operator_twin", "hrv_analyser", "decision_maker", "pareto_store", "executor"]


class Machine:
    """systemd as PID 1 of its own namespaces, and ways to run commands in them."""

    def __init__(self, stage: Path) -> None:
        self.stage = stage
        (stage / "src").mkdir(parents=True)
        (stage / "ov").mkdir()
        boot = stage / "boot.sh"
        boot.write_text(BOOT)
        self.log = open(stage / "systemd.log", "w")  # noqa: SIM115 (open for the machine's life)
        self.unshare = subprocess.Popen(
            [
                "unshare",
                "--fork",
                "--pid",
                "--mount",
                "--mount-proc",
                "bash",
                str(boot),
                str(stage),
                str(REPO),
            ],
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )
        self.pid = 0
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and self.unshare.poll() is None:
            kids = subprocess.run(
                ["pgrep", "-P", str(self.unshare.pid)], capture_output=True, text=True, check=False
            ).stdout.split()
            if kids and Path(f"/proc/{kids[0]}/comm").read_text().strip() == "systemd":
                self.pid = int(kids[0])
                state = self.sh("systemctl is-system-running", check=False).stdout.strip()
                if state in ("running", "degraded"):
                    return
            time.sleep(0.2)
        raise AssertionError(f"systemd did not boot: {(stage / 'systemd.log').read_text()[-2000:]}")

    def put(self, path: str, data: bytes, owner: str = "root") -> None:
        """Write a file from inside (through /proc/PID/root, overlayfs gave ESTALE on a later unlink)."""
        r = subprocess.run(
            [
                "nsenter",
                "-t",
                str(self.pid),
                "-m",
                "-p",
                "sh",
                "-c",
                f'cat > "$0" && chown {owner} "$0"',
                path,
            ],
            input=data,
            capture_output=True,
            timeout=60,
            check=False,
        )
        assert r.returncode == 0, r.stderr

    def sh(self, cmd: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess[str]:
        uv_dir = Path(shutil.which("uv") or "uv").parent  # the rest as here: proxies, certificates
        env = os.environ | {"PATH": f"{uv_dir}:/usr/sbin:/usr/bin:/sbin:/bin", "HOME": "/root"}
        r = subprocess.run(
            ["nsenter", "-t", str(self.pid), "-m", "-p", "bash", "-c", cmd],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
            check=False,
        )
        if check and r.returncode != 0:
            raise AssertionError(f"{cmd}: exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
        return r

    def path(self, p: str) -> Path:
        """A file as the machine sees it (its /etc is an overlay)."""
        return Path(f"/proc/{self.pid}/root{p}")

    def show(self, unit: str, *props: str) -> dict[str, str]:
        out = self.sh(f"systemctl show {unit} -p {','.join(props)}").stdout
        return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)

    def main_pid(self, unit: str) -> int:
        return int(self.show(unit, "MainPID")["MainPID"])

    def until(self, what: str, cond: Callable[[], object], timeout: float) -> float:
        """Seconds until ``cond()`` holds (polling systemd's own state: no timing is assumed)."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if cond():
                return time.monotonic() - t0
            time.sleep(0.2)
        journal = self.sh("journalctl -n 80 --no-pager -o short", check=False).stdout
        raise AssertionError(f"{what}: not within {timeout} s; the journal's end:\n{journal}")

    def close(self) -> None:
        if self.pid:
            self.sh("systemctl poweroff", check=False)
        try:
            self.unshare.wait(60)
        except subprocess.TimeoutExpired:
            os.kill(self.pid, signal.SIGKILL)
            self.unshare.wait(30)
        self.log.close()


def _booted() -> Iterator[Machine]:
    stage = Path("/dev/shm") / f"cadence-systemd-{uuid.uuid4().hex[:8]}"
    m = Machine(stage)
    try:
        yield m
    finally:
        m.close()
        shutil.rmtree(stage, ignore_errors=True)


machine = pytest.fixture(_booted)
second_machine = pytest.fixture(_booted)  # another host of the same cell (the network is shared)


def _speed_ups(m: Machine, example_sets: Path) -> None:
    """The tests' settings, as an admin would set them: short windows, and sets already planned (the
    store serves them without planning)."""
    m.put("/etc/cadence/hrv_analyser.env", b"CADENCE_HRV_ANALYSER_WINDOW_S=10\n")
    m.put("/var/lib/cadence/pareto.sqlite", example_sets.read_bytes(), "cadence:cadence")


def _account(m: Machine, tmp: Path, name: str) -> BusConfig:
    p = tmp / f"{name}.json5"
    p.write_text(m.path(f"/etc/cadence/credentials/{name}.json5").read_text())
    return BusConfig(config_file=str(p))


@needs_root
@pytest.mark.asyncio
async def test_the_cell_installs_starts_and_survives_under_systemd(
    machine: Machine, tmp_path: Path, example_sets: Path
) -> None:
    m = machine
    port = free_port()
    t0 = time.monotonic()
    r = m.sh(
        f"{sys.executable} -m cadence install --robot sim --strap twin --port {port} --router-host localhost",
        timeout=900,
    )
    install_s = time.monotonic() - t0
    print(f"\ninstall: {install_s:.0f} s\n{r.stdout}")
    # the interpreter the units run is one the service user can use, not a link into root's home
    venv_python = m.sh("readlink -f /opt/cadence/.venv/bin/python").stdout.strip()
    assert not venv_python.startswith(("/root", "/home")), venv_python
    m.sh("runuser -u cadence -- /opt/cadence/.venv/bin/cadence --help >/dev/null")
    _speed_ups(m, example_sets)

    t_start = time.monotonic()
    m.sh("systemctl start cadence.target")
    m.until(
        "every unit active (running), READY=1",
        lambda: all(
            m.show(f"cadence-{u}", "ActiveState", "SubState")
            == {"ActiveState": "active", "SubState": "running"}
            for u in UNITS
        ),
        120,
    )
    ready_s = time.monotonic() - t_start

    async with await Bus.open(_account(m, tmp_path, "monitor"), CELL) as monitor:
        selections = monitor.subscribe(monitor.key("decision/selection"), Selection)
        windows = monitor.subscribe(monitor.key("hrv/window"), HrvWindow)
        cycles = monitor.subscribe(monitor.key("robot/cycle"), CycleReport)
        await selections.receive(120)
        first_selection_s = time.monotonic() - t_start
        await windows.receive(120)
        _, cycle = await cycles.receive(300)
        first_cycle_s = time.monotonic() - t_start

        # kill -9: systemd restarts it, and the cell goes on (a new window reaches the decision maker)
        pid = m.main_pid("cadence-decision_maker")
        t_kill = time.monotonic()
        m.sh(f"kill -KILL {pid}")  # a pid of the machine's own PID namespace
        m.until(
            "the decision maker restarted", lambda: m.main_pid("cadence-decision_maker") not in (0, pid), 60
        )
        m.until(
            "the decision maker active again",
            lambda: m.show("cadence-decision_maker", "SubState")["SubState"] == "running",
            60,
        )
        kill_restart_s = time.monotonic() - t_kill
        while True:  # the republished selection of the new process
            _, s = await selections.receive(60)
            if s.t_ns > 0 and time.monotonic() - t_kill > kill_restart_s:
                break

        # kill -STOP: the frozen loop stops pinging; the watchdog (WatchdogSec=10s) has it restarted
        pid = m.main_pid("cadence-hrv_analyser")
        t_stop = time.monotonic()
        m.sh(f"kill -STOP {pid}")
        m.until(
            "the watchdog restarted the analyser",
            lambda: m.main_pid("cadence-hrv_analyser") not in (0, pid),
            60,
        )
        stop_restart_s = time.monotonic() - t_stop
        assert m.show("cadence-hrv_analyser", "NRestarts")["NRestarts"] != "0"
        why = m.sh("journalctl -u cadence-hrv_analyser --no-pager -o cat").stdout
        assert "Watchdog timeout" in why, why[-2000:]  # systemd's own word: its watchdog, not a crash
        await windows.receive(120)  # windows again, from the new process

        # ACL: the analyser's own account cannot publish a selection
        async with await Bus.open(_account(m, tmp_path, "hrv_analyser"), CELL) as rogue:
            forged = Selection(t_ns=1, seq=999_999, k=1, n=15, delta=-1, reason="stress", window_end_ns=1)
            for _ in range(5):
                put(rogue, rogue.key("decision/selection"), forged, block=True)
            deadline = time.monotonic() + 5
            while time.monotonic() < deadline:
                try:
                    _, s = await selections.receive(deadline - time.monotonic())
                except TimeoutError:
                    break
                assert s.seq != 999_999, "a forged selection got through the router"

    # nobody but the router listens; a session without the cell's certificate is refused
    listening = m.sh("ss -ltnpH").stdout
    cadence_pids = {str(m.main_pid(f"cadence-{u}")) for u in UNITS}
    listeners = [line for line in listening.splitlines() if any(f"pid={p}," in line for p in cadence_pids)]
    assert listeners, listeners
    assert all(f":{port} " in line for line in listeners), listeners
    stranger = BusConfig(mode="client", connect=[f"tls/127.0.0.1:{port}"], config_file=None)
    with pytest.raises(Exception):  # noqa: B017 (Zenoh raises its own error type when it cannot connect)
        await Bus.open(stranger, CELL)

    t_halt = time.monotonic()
    m.sh("systemctl stop cadence.target", timeout=120)  # returns with the target's job; the units' follow
    m.until(
        "every unit stopped",
        lambda: all(m.show(f"cadence-{u}", "ActiveState")["ActiveState"] == "inactive" for u in UNITS),
        60,
    )
    stop_s = time.monotonic() - t_halt
    for u in UNITS:
        st = m.show(f"cadence-{u}", "ActiveState", "Result", "ExecMainStatus")
        log = m.sh(f"journalctl -u cadence-{u} -n 8 --no-pager -o cat", check=False).stdout
        assert st["ActiveState"] == "inactive", (u, st, log)
        assert st["Result"] == "success", (u, st, log)
        assert st["ExecMainStatus"] == "0", (u, st, log)
    journal = m.sh("journalctl -u cadence-decision_maker -o cat --no-pager").stdout.splitlines()
    records = [json.loads(line) for line in journal if line.startswith("{")]
    assert records, journal[:5]
    assert all("msg" in r or "message" in r for r in records), journal[:5]

    # uninstall: what the install wrote is gone, the data is kept
    m.sh(f"{sys.executable} -m cadence uninstall")
    for gone in ("/etc/cadence", "/etc/systemd/system/cadence-executor.service", "/opt/cadence/.venv"):
        assert not m.path(gone).exists(), gone
    assert m.path("/var/lib/cadence/pareto.sqlite").exists()

    print(
        f"units active (READY=1): {ready_s:.1f} s after systemctl start;"
        f" first selection {first_selection_s:.1f} s;"
        f" first cycle {first_cycle_s:.1f} s (k per path {cycle.k_per_path});"
        f" kill -9 → running again {kill_restart_s:.1f} s; kill -STOP → restarted by the watchdog"
        f" {stop_restart_s:.1f} s; systemctl stop {stop_s:.1f} s; {len(records)} JSON journal lines"
    )


@needs_root
@pytest.mark.asyncio
async def test_a_second_host_joins_the_cell_with_the_first_hosts_bundle(
    machine: Machine, second_machine: Machine, tmp_path: Path, example_sets: Path
) -> None:
    """The README's two-host layout: the cell PC runs the router, the executor and the gateway; the
    second host joins with the first's cell.json and runs the store, the analyser and the decision maker.
    A cycle needs both: the executor's sets and selections come from the other host."""
    cell_pc, second = machine, second_machine
    port = free_port()
    install = f"{sys.executable} -m cadence install --robot sim --strap twin"
    cell_pc.sh(
        f"{install} --services router,executor,operator_twin --port {port} --router-host 127.0.0.1",
        timeout=900,
    )
    second.put("/root/cell.json", cell_pc.path("/etc/cadence/credentials/cell.json").read_bytes())
    second.sh(
        f"{install} --join /root/cell.json --services pareto_store,hrv_analyser,decision_maker", timeout=900
    )
    assert not second.path("/etc/cadence/credentials/router.json5").exists()
    assert not second.path("/etc/systemd/system/cadence-executor.service").exists()
    _speed_ups(cell_pc, example_sets)
    _speed_ups(second, example_sets)
    for m in (cell_pc, second):
        m.sh("systemctl start cadence.target")
    async with await Bus.open(_account(cell_pc, tmp_path, "monitor"), CELL) as monitor:
        cycles = monitor.subscribe(monitor.key("robot/cycle"), CycleReport)
        _, cycle = await cycles.receive(300)
    assert set(cycle.k_per_path) == set(load_task(EXAMPLE_TASK).paths)
    for m, units in (
        (cell_pc, ("router", "executor", "operator_twin")),
        (second, ("pareto_store", "decision_maker")),
    ):
        for u in units:
            assert m.show(f"cadence-{u}", "NRestarts")["NRestarts"] == "0", u  # nobody crashed to get here
