"""deploy/: the systemd units, rendered from the registry (services/registry.py) as `cadence install` writes
them, verify and score under a security threshold. The router's ACL is generated (cadence/deploy/cell.py)
and tested against a real router in tests/cadence/deploy/test_cell.py."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from services.registry import SERVICES, unit
from tests.support.paths import REPO

DEPLOY = REPO / "deploy"
TEMPLATE = (DEPLOY / "systemd" / "cadence-service.in").read_text()
# every unit as installed: the services' from the template, the router's and the target as written
UNITS = {f"cadence-{s.name}.service": unit(s, TEMPLATE) for s in SERVICES if s.unit} | {
    p.name: p.read_text()
    for p in (DEPLOY / "systemd").glob("cadence[-.]*")
    if p.suffix in (".service", ".target")
}
needs_systemd = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed (.ci/run installs it)"
)
THRESHOLD = 20  # systemd-analyze's exposure x 10: the units score 1.5 to 1.7 ("OK") today


@pytest.fixture
def installed_units(tmp_path: Path) -> list[Path]:
    """The units as they would be installed, with ExecStart pointing at this checkout's `cadence`."""
    cadence = Path(sys.executable).parent / "cadence"
    out = []
    for name, text in UNITS.items():
        p = tmp_path / name
        p.write_text(text.replace("/opt/cadence/.venv/bin/cadence", str(cadence)))
        out.append(p)
    return out


def test_every_service_has_a_unit_and_the_executor_gets_real_time_rights() -> None:
    from schemas.topology import SERVICES as GRAPH_SERVICES

    names = {n.removeprefix("cadence-").removesuffix(".service") for n in UNITS if n.endswith(".service")}
    assert names == set(GRAPH_SERVICES) | {"router"}
    for name, text in UNITS.items():
        if name.endswith(".target"):
            continue
        for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "EnvironmentFile=", "User=cadence",
                     "ProtectSystem=strict"):  # fmt: skip
            assert line in text, f"{name} has no {line}"
    for name in names - {"router"}:
        assert f"ExecStart=/opt/cadence/.venv/bin/cadence run {name} " in UNITS[f"cadence-{name}.service"]
    executor = UNITS["cadence-executor.service"]
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
    assert r.returncode == 0, r.stderr
    assert not ours, r.stderr


@needs_systemd
@pytest.mark.parametrize("name", [n for n in UNITS if n.endswith(".service")])
def test_each_unit_is_hardened(name: str, installed_units: list[Path]) -> None:
    path = next(p for p in installed_units if p.name == name)
    r = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", f"--threshold={THRESHOLD}", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    score = re.search(r"Overall exposure level for \S+: ([\d.]+)", r.stdout)
    print(f"{name}: {score.group(1) if score else '?'}")
    assert r.returncode == 0, r.stdout[-2000:]
