"""An installed Cadence is whole (issue 16): the wheel carries the example task and the deploy templates,
and `cadence demo` runs from a fresh venv outside the checkout. And a store or a demo that dies, even of
SIGKILL, takes its children with it: the planning worker, the services."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from common.runtime.resources import EXAMPLE_TASK
from tests.support.paths import REPO

needs_uv = pytest.mark.skipif(shutil.which("uv") is None, reason="uv is not on PATH (.ci/run installs it)")


def _run(cmd: list[str], cwd: Path, timeout: float) -> str:
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False)
    assert r.returncode == 0, f"{' '.join(cmd)}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout


@needs_uv
def test_the_wheel_runs_the_demo_from_a_fresh_venv(tmp_path: Path, example_sets: Path) -> None:
    uv = shutil.which("uv")
    assert uv is not None
    _run([uv, "build", "--wheel", "-o", str(tmp_path / "dist"), str(REPO)], REPO, 300)
    wheel = next((tmp_path / "dist").glob("cadence-*.whl"))
    req = tmp_path / "requirements.txt"
    _run(
        [uv, "export", "--frozen", "--no-dev", "--no-emit-project", "--no-hashes", "-o", str(req)], REPO, 120
    )
    venv = tmp_path / "venv"
    _run([uv, "venv", "--python", sys.executable, str(venv)], tmp_path, 120)
    _run(
        [uv, "pip", "install", "--python", str(venv / "bin" / "python"), "-r", str(req), str(wheel)],
        tmp_path,
        600,
    )
    work = tmp_path / "elsewhere"  # not the checkout: nothing may be found relative to it
    (work / "out" / "data").mkdir(parents=True)
    # the sets, planned once per test run: the store checks them against the task the wheel carries
    shutil.copy(example_sets, work / "out" / "data" / "pareto.sqlite")
    _run([str(venv / "bin" / "cadence"), "demo", "--duration", "60", "--no-live", "--out", "out"], work, 600)
    s = json.loads((work / "out" / "summary.json").read_text())
    assert s["selections"]
    assert all(code == 0 for code in s["exit_codes"].values())
    site = next((venv / "lib").glob("python3*/site-packages"))
    assert (site / "cadence" / "deploy" / "files" / "tasks" / "box_filling.toml").exists()
    assert (site / "cadence" / "deploy" / "files" / "systemd" / "cadence-service.in").exists()
    # the units `cadence install` writes, rendered by the installed package from its own template
    render = (
        "from common.runtime.resources import DEPLOY; from services.registry import BY_NAME, unit; "
        "print(unit(BY_NAME['executor'], (DEPLOY / 'systemd' / 'cadence-service.in').read_text()))"
    )
    executor_unit = _run([str(venv / "bin" / "python"), "-c", render], work, 60)
    assert "ExecStart=/opt/cadence/.venv/bin/cadence run executor" in executor_unit
    assert "LimitRTPRIO=90" in executor_unit
    for package in ("cadence", "common", "schemas", "services"):  # PEP 561: their type hints are used
        assert (site / package / "py.typed").exists()
    version = _run([str(venv / "bin" / "cadence"), "--version"], work, 60)
    assert version.strip() == "cadence 0.1.0"


def _descendants(pid: int) -> list[int]:
    out = subprocess.run(
        ["pgrep", "-P", str(pid)], capture_output=True, text=True, check=False
    ).stdout.split()
    kids = [int(p) for p in out]
    return kids + [d for k in kids for d in _descendants(k)]


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _until(cond: Callable[[], object], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(what)
        time.sleep(0.1)


def _planning(demo: int, not_store: int | None = None) -> tuple[int, int]:
    """The demo's store and its planning worker (a spawned process; the resource tracker is not one)."""
    found: list[tuple[int, int]] = []

    def look() -> bool:
        for store in _descendants(demo):
            if store == not_store:
                continue
            for kid in _descendants(store):
                with contextlib.suppress(OSError):
                    if b"spawn_main" in Path(f"/proc/{kid}/cmdline").read_bytes():
                        found.append((store, kid))
                        return True
        return False

    _until(look, 120, "the store's planning worker never started")
    return found[0]


@pytest.mark.skipif(shutil.which("pgrep") is None, reason="needs pgrep")
def test_a_killed_store_or_demo_leaves_no_process_behind(tmp_path: Path) -> None:
    task = tmp_path / "reseeded.toml"  # the example task's shipped sets are served without planning
    task.write_text(EXAMPLE_TASK.read_text().replace("seed = 1", "seed = 2"))
    demo = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cadence",
            "demo",
            "--processes",
            "--duration",
            "600",
            "--no-live",
            "--task",
            str(task),
            "--out",
            str(tmp_path / "o"),
        ],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # so that nothing of it is this test's process group
    )
    try:
        # a SIGKILLed store: its planning worker goes with it
        store, worker = _planning(demo.pid)
        os.kill(store, signal.SIGKILL)
        _until(lambda: not _alive(worker), 30, f"the planning worker {worker} outlived its SIGKILLed store")
        # the demo restarts the store, which plans again; a SIGKILLed demo: every service and worker goes
        _planning(demo.pid, not_store=store)
        tree = _descendants(demo.pid)
        demo.send_signal(signal.SIGKILL)
        demo.wait(10)
        _until(lambda: not any(_alive(p) for p in tree), 30, "a process outlived the SIGKILLed demo")
    finally:
        for p in _descendants(demo.pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(p, signal.SIGKILL)
        if demo.poll() is None:
            demo.kill()
