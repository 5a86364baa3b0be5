"""deploy/: the systemd units verify and score under a security threshold. The router's ACL is generated
(common/runtime/cell.py) and tested against a real router in tests/test_cell.py."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO

DEPLOY = REPO / "deploy"
UNITS = sorted((DEPLOY / "systemd").glob("*.service"))
needs_systemd = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed (.ci/run installs it)"
)
THRESHOLD = 20  # systemd-analyze's exposure x 10: the units score 1.5 to 1.7 ("OK") today


@pytest.fixture
def installed_units(tmp_path: Path) -> list[Path]:
    """The units as they would be installed, with ExecStart pointing at this checkout's `cadence`."""
    cadence = Path(sys.executable).parent / "cadence"
    out = []
    for unit in [*UNITS, DEPLOY / "systemd" / "cadence.target"]:
        p = tmp_path / unit.name
        p.write_text(unit.read_text().replace("/opt/cadence/.venv/bin/cadence", str(cadence)))
        out.append(p)
    return out


def test_every_service_has_a_unit_and_the_executor_gets_real_time_rights() -> None:
    from cadence.cli import SERVICES

    names = {u.stem.removeprefix("cadence-") for u in UNITS}
    assert names == (set(SERVICES) - {"ur_emulator"}) | {"router"}
    for unit in UNITS:
        text = unit.read_text()
        assert "Type=notify" in text and "WatchdogSec=" in text and "Restart=on-failure" in text
        assert "EnvironmentFile=" in text and "User=cadence" in text and "ProtectSystem=strict" in text
    executor = (DEPLOY / "systemd" / "cadence-executor.service").read_text()
    assert all(k in executor for k in ("CPUAffinity=", "LimitRTPRIO=", "LimitMEMLOCK="))
    # DESIGN §11: FIFO for the servo thread alone, never the whole process
    settings = [line for line in executor.splitlines() if not line.startswith("#")]
    assert not any(line.startswith(("CPUSchedulingPolicy", "RestrictRealtime=yes")) for line in settings)


@needs_systemd
def test_the_units_verify(installed_units: list[Path]) -> None:
    r = subprocess.run(
        ["systemd-analyze", "verify", "--recursive-errors=yes", *map(str, installed_units)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    ours = [line for line in r.stderr.splitlines() if "cadence" in line]
    assert r.returncode == 0 and not ours, r.stderr


@needs_systemd
@pytest.mark.parametrize("unit", [u.name for u in UNITS])
def test_each_unit_is_hardened(unit: str, installed_units: list[Path]) -> None:
    path = next(p for p in installed_units if p.name == unit)
    r = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", f"--threshold={THRESHOLD}", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    score = re.search(r"Overall exposure level for \S+: ([\d.]+)", r.stdout)
    print(f"{unit}: {score.group(1) if score else '?'}")
    assert r.returncode == 0, r.stdout[-2000:]
