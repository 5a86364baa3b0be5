"""A deployed cell's bus (cadence/deploy/cell.py, pki.py): the ACL follows the graph, and a real router with
the generated config holds: mTLS and passwords both required, each account publishes only its keys.
Also the secure default (a peer listens on loopback only), the install's dry run, and children that die
with their parent."""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cadence.deploy.cell import (
    ACCOUNTS,
    PLANT_KEYS,
    Tls,
    access_control,
    askers,
    client_config,
    identity,
    merged,
    publishers,
    router_config,
    users_file,
)
from cadence.deploy.install import Bundle, Options, cell_accounts, new_bundle, plan
from cadence.deploy.pki import common_name, issue, make_ca
from common.runtime.bus import Bus, BusConfig
from schemas import HrvWindow, OperatorSignal, Selection, Separation, ServiceStatus
from schemas.topology import HEALTH, OPERATOR_SIGNAL, SELECTION, SERVICES, TOPICS, key_for
from services.executor.settings import SourceSettings
from tests.support.cell import CELL, account_file, config_file, free_port, put
from tests.support.paths import REPO


def _includes(rule_key: str, key: str) -> bool:
    """Zenoh's inclusion for the ACL's keys: exact, or a family ending in ``/**``."""
    return rule_key == key or (rule_key.endswith("/**") and key.startswith(rule_key[:-2]))


def test_every_topic_has_exactly_its_publishers_and_its_askers_in_the_acl() -> None:
    acl = access_control("c1")
    rules = {r["id"]: r for r in acl["rules"]}

    def allowed(rule: str, key: str) -> set[str]:
        return {
            a
            for a in ACCOUNTS
            if any(_includes(k, key) for k in rules.get(f"c1: {rule} {a}", {}).get("key_exprs", []))
        }

    for t in TOPICS:
        key = key_for(t, "c1").replace("*", "x")
        if t.scope == "plant":  # under cadence/plant/ (sets by hash): questions and answers, no put
            assert allowed("plant keys", key) == publishers(t) | askers(t) == {"pareto_store"}, t.suffix
            assert allowed("publish", key) == allowed("ask", key) == set(), t.suffix
            continue
        if t.owned:  # each member its own account's (a declared sensor's key: below), never a role's
            assert allowed("publish", key) == set(), t.suffix
        elif t is not HEALTH:  # health/<account>: each its own (below)
            assert allowed("publish", key) == publishers(t), t.suffix
        # the ACL names families (pareto/**), so who may ask a set may ask its members too
        assert askers(t) <= allowed("ask", key), t.suffix
    assert publishers(SELECTION) == {"decision_maker"}
    # the twin runs in the gateway; the executor publishes the buttons on its controller's inputs
    assert publishers(OPERATOR_SIGNAL) == {"operator", "operator_twin", "executor"}
    assert allowed("ask", "cadence/c1/robot/resume") == {"operator"}  # it changes what the robot does
    assert allowed("ask", "cadence/c1/decision/condition") == {"operator"}  # a study session's switch
    assert allowed("ask", "cadence/c1/decision/selection") == {"executor", "operator", "monitor"}
    assert allowed("ask", "cadence/c1/ecg/samples") == set()
    for p in acl["policies"]:
        assert all(rule in rules for rule in p["rules"])
    # who says where people are: the sensors' account, and the twin in simulation; never the HMI's
    assert allowed("publish", "cadence/c1/operator/separation") == {"separation_sensor", "operator_twin"}
    for service in SERVICES:  # each speaks for its own health, and for no one else's
        assert allowed("publish", f"cadence/c1/health/{service}") == {service}


@pytest.mark.asyncio
async def test_one_scanners_account_cannot_speak_as_another_declared_source(tmp_path: Path) -> None:
    """Each declared source its own account (`cadence install --scanner`), which may put on that source's
    own key and nowhere else (issue 74: one account spoke for every scanner, so any adapter could keep a
    dead scanner heard). On a real router with the install's files: scanner:front's account puts under
    scanner:back's key, and on the shared key, and then on its own; the monitor's first message is its
    own, put last: the router dropped the other two."""
    scanners = (
        SourceSettings.parse("scanner:front:0,0,0:legs"),
        SourceSettings.parse("scanner:back:2,0,180:legs"),
    )
    opts = Options(robot="sim", strap="twin", scanners=scanners)
    bundle = new_bundle(opts)
    ca, passwords = bundle.ca, bundle.passwords
    assert {"sensor_scanner_front", "sensor_scanner_back"} <= set(passwords)
    files = {f.path.name: f.text for f in plan(opts, bundle).files}
    assert "sensor_scanner_front.json5" in files and "sensor_scanner_back.json5" in files
    endpoint = [f"tls/127.0.0.1:{free_port()}"]
    (tmp_path / "users.txt").write_text(users_file(CELL, passwords))
    leaf = issue(ca, identity(CELL, "router"), CELL, ["127.0.0.1"])
    cfg = router_config(CELL, endpoint, Tls(ca.cert, leaf.cert, leaf.key), str(tmp_path / "users.txt"),
                        sensors=("scanner:front", "scanner:back"))  # fmt: skip
    router = config_file(tmp_path, "router", cfg)

    def account(name: str) -> BusConfig:
        return account_file(tmp_path, ca, CELL, name, passwords[name], endpoint)

    back = Separation(t_ns=3, seq=0, distance_m=100.0, source="scanner:back")
    front = Separation(t_ns=3, seq=1, distance_m=0.6, source="scanner:front")
    async with (
        await Bus.open(router, CELL),
        await Bus.open(account("monitor"), CELL) as monitor,
        await Bus.open(account("sensor_scanner_front"), CELL) as sensor,
    ):
        seen = monitor.subscribe(monitor.key("operator/separation/**"), Separation)
        await sensor.until_subscribed(sensor.key("operator/separation/scanner_front"), 10)
        put(sensor, sensor.key("operator/separation/scanner_back"), back, block=True)  # another's key
        put(sensor, sensor.key("operator/separation"), back, block=True)  # the shared key: not its own
        put(sensor, sensor.key("operator/separation/scanner_front"), front, block=True)
        assert (await seen.receive(10))[1] == front
        assert seen.pending == 0


def test_a_cell_with_a_strap_gives_the_twin_no_account_at_all() -> None:
    strap = access_control("c1", cell_accounts("Polar H10"))
    named = {a for p in strap["policies"] for a in p["subjects"]}
    assert "c1-operator_twin" not in named
    assert {"c1-ecg_gateway", "c1-separation_sensor", "c1-executor"} <= named
    twin = access_control("c1", cell_accounts("twin"))
    assert "c1-operator_twin" in {a for p in twin["policies"] for a in p["subjects"]}


def cell_router(tmp: Path, ca, passwords: dict[str, str], endpoint: list[str]) -> BusConfig:
    """The cell's router as `cadence install` writes it: its users file, its certificate from the cell's CA
    (``ca``, a ``cadence.deploy.pki.Pem``), listening on ``endpoint``."""
    (tmp / "users.txt").write_text(users_file(CELL, passwords))
    leaf = issue(ca, identity(CELL, "router"), CELL, ["127.0.0.1"])
    cfg = router_config(CELL, endpoint, Tls(ca.cert, leaf.cert, leaf.key), str(tmp / "users.txt"))
    return config_file(tmp, "router", cfg)


@pytest.mark.asyncio
async def test_the_router_requires_the_cells_certificate_and_the_accounts_own_keys(tmp_path: Path) -> None:
    ca = make_ca(CELL)
    passwords = {a: f"pw-{a}" for a in ACCOUNTS}
    endpoint = [f"tls/127.0.0.1:{free_port()}"]
    router = cell_router(tmp_path, ca, passwords, endpoint)
    certs = {a: issue(ca, identity(CELL, a), CELL, [a]) for a in ACCOUNTS}
    assert common_name(certs["executor"].cert) == f"{CELL}-executor"

    def account(cert: str, user: str) -> BusConfig:
        c = certs[cert]
        return config_file(
            tmp_path,
            f"{cert}-{user}",
            client_config(CELL, user, passwords[user], endpoint, Tls(ca.cert, c.cert, c.key)),
        )

    sel = Selection(t_ns=1, seq=7, k=3, n=15, delta=-1, reason="stress", window_end_ns=1)
    window = HrvWindow(
        t_ns=2, seq=0, start_ns=0, end_ns=2, mean_rr_s=0.8, n_beats=3, excluded_fraction=0.0, quality="good"
    )
    async with (
        await Bus.open(router, CELL),
        await Bus.open(account("monitor", "monitor"), CELL) as monitor,
        await Bus.open(account("decision_maker", "decision_maker"), CELL) as decider,
        await Bus.open(account("hrv_analyser", "hrv_analyser"), CELL) as analyser,
        # a stolen password with another account's certificate
        await Bus.open(account("monitor", "decision_maker"), CELL) as mixed,
    ):
        selections = monitor.subscribe(monitor.key("decision/selection"), Selection)
        windows = monitor.subscribe(monitor.key("hrv/window"), HrvWindow)
        await analyser.until_subscribed(analyser.key("hrv/window"), 10)
        await decider.until_subscribed(decider.key("decision/selection"), 10)
        put(analyser, analyser.key("hrv/window"), window, block=True)  # its own key: allowed
        assert (await windows.receive(10))[1] == window
        for rogue in (analyser, mixed):
            put(rogue, rogue.key("decision/selection"), sel, block=True)  # forbidden
        put(analyser, analyser.key("hrv/window"), window, block=True)  # after them on the same links
        put(mixed, mixed.key("hrv/window"), window, block=True)  # (the monitor's rights: forbidden too)
        await windows.receive(10)
        put(decider, decider.key("decision/selection"), sel, block=True)
        _, got = await selections.receive(10)
        assert got == sel
        assert selections.pending == 0  # the decision maker's, and only it
        assert windows.pending == 0
    # where a person is: the sensor's account may say it, the HMI's operator account may not; and no
    # service speaks for another's health. (A forbidden put, then an allowed one on the same link: the
    # second's arrival says the first would have come.)
    near = Separation(t_ns=3, seq=0, distance_m=0.6, source="scanner:front")
    far = Separation(t_ns=3, seq=1, distance_m=100.0, source="scanner:front")
    signal = OperatorSignal(t_ns=3, seq=0, name="part")
    theirs = ServiceStatus(
        t_ns=4, seq=0, service="decision_maker", state="serving", uptime_s=1.0, counters={}
    )
    own = ServiceStatus(t_ns=4, seq=0, service="executor", state="serving", uptime_s=1.0, counters={})
    async with (
        await Bus.open(router, CELL),
        await Bus.open(account("monitor", "monitor"), CELL) as monitor,
        await Bus.open(account("separation_sensor", "separation_sensor"), CELL) as sensor,
        await Bus.open(account("operator", "operator"), CELL) as hmi,
        await Bus.open(account("executor", "executor"), CELL) as executor,
    ):
        seps = monitor.subscribe(monitor.key("operator/separation"), Separation)
        signals = monitor.subscribe(monitor.key("operator/signal"), OperatorSignal)
        dm_health = monitor.subscribe(monitor.key("health/decision_maker"), ServiceStatus)
        ex_health = monitor.subscribe(monitor.key("health/executor"), ServiceStatus)
        for session, suffix in ((hmi, "operator/separation"), (hmi, "operator/signal"),
                                (sensor, "operator/separation"), (executor, "health/decision_maker"),
                                (executor, "health/executor")):  # fmt: skip
            await session.until_subscribed(session.key(suffix), 10)
        put(hmi, hmi.key("operator/separation"), far, block=True)  # forbidden
        put(hmi, hmi.key("operator/signal"), signal, block=True)
        put(executor, executor.key("health/decision_maker"), theirs, block=True)  # forbidden
        put(executor, executor.key("health/executor"), own, block=True)
        put(sensor, sensor.key("operator/separation"), near, block=True)
        assert (await signals.receive(10))[1] == signal
        assert (await ex_health.receive(10))[1] == own
        assert (await seps.receive(10))[1] == near
        assert seps.pending == 0
        assert dm_health.pending == 0
    # no certificate of the cell: the router refuses the link
    stranger = {"mode": "client", "connect": {"endpoints": endpoint, "timeout_ms": 2000}}
    stranger["transport"] = {
        "auth": {"usrpwd": {"user": identity(CELL, "monitor"), "password": passwords["monitor"]}}
    }
    with pytest.raises(Exception):  # noqa: B017 (Zenoh's own error type)
        async with (
            await Bus.open(router, CELL),
            await Bus.open(config_file(tmp_path, "stranger", stranger), CELL),
        ):
            pass


def test_many_cells_rules_on_one_router_grant_each_identity_only_its_own_cells_keys() -> None:
    """A line's or a plant's router holds several cells' rules (issue 58): with bare role names, cell1's
    separation sensor could say where people are in cell2. Every rule names keys of one cell, and every
    policy applies its cell's rules to that cell's identities only, so under default deny no role of one
    cell may publish, answer, query or even read under another's keys."""
    cells = ("c1", "c2", "line-3")
    acl = merged(*(access_control(c) for c in cells))
    assert acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    assert len(rules) == len(acl["rules"])  # no id of one cell's rules shadows another's
    assert len({s["id"] for s in acl["subjects"]}) == len(acl["subjects"]) == len(cells) * len(ACCOUNTS)
    for policy in acl["policies"]:
        (cell,) = {rules[r]["id"].split(": ")[0] for r in policy["rules"]}
        for r in policy["rules"]:
            # the plant's own keys (a set by its hash) are every cell's to ask and answer, by design
            assert all(k.startswith(f"cadence/{cell}/") or k in PLANT_KEYS for k in rules[r]["key_exprs"]), r
        assert all(s.rsplit("-", 1)[0] == cell for s in policy["subjects"]), policy
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert subjects["line-3-separation_sensor"]["cert_common_names"] == ["line-3-separation_sensor"]
    assert subjects["line-3-separation_sensor"]["usernames"] == ["line-3-separation_sensor"]


@pytest.mark.asyncio
async def test_one_cells_sensor_cannot_say_where_people_are_in_another_on_a_shared_router(
    tmp_path: Path,
) -> None:
    """Two cells behind one router with their merged rules, over mTLS (one plant CA): cell c1's separation
    sensor puts a distance on c2's key, then on its own; c1's monitor gets its own, and c2's monitor's
    first message is c2's own sensor's, put after that: the router dropped the other cell's."""
    ca = make_ca("plant")
    cells = ("c1", "c2")
    passwords = {c: {a: f"pw-{c}-{a}" for a in ACCOUNTS} for c in cells}
    (tmp_path / "users.txt").write_text("".join(users_file(c, passwords[c]) for c in cells))
    endpoint = [f"tls/127.0.0.1:{free_port()}"]
    leaf = issue(ca, "plant-router", "plant", ["127.0.0.1"])
    cfg = router_config("c1", endpoint, Tls(ca.cert, leaf.cert, leaf.key), str(tmp_path / "users.txt"))
    cfg["access_control"] = merged(*(access_control(c) for c in cells))
    router = config_file(tmp_path, "router", cfg)

    def account(cell: str, name: str) -> BusConfig:
        return account_file(tmp_path, ca, cell, name, passwords[cell][name], endpoint)

    theirs = Separation(t_ns=3, seq=0, distance_m=100.0, source="scanner:front")
    own = Separation(t_ns=3, seq=1, distance_m=0.6, source="scanner:front")
    later = Separation(t_ns=4, seq=2, distance_m=2.0, source="scanner:back")
    async with (
        await Bus.open(router, "c1"),
        await Bus.open(account("c1", "monitor"), "c1") as m1,
        await Bus.open(account("c2", "monitor"), "c2") as m2,
        await Bus.open(account("c1", "separation_sensor"), "c1") as s1,
        await Bus.open(account("c2", "separation_sensor"), "c2") as s2,
    ):
        seen1 = m1.subscribe(m1.key("operator/separation"), Separation)
        seen2 = m2.subscribe(m2.key("operator/separation"), Separation)
        await s1.until_subscribed(s1.key("operator/separation"), 10)
        await s2.until_subscribed(s2.key("operator/separation"), 10)
        put(s1, "cadence/c2/operator/separation", theirs, block=True)  # another cell's key: forbidden
        put(s1, s1.key("operator/separation"), own, block=True)
        assert (await seen1.receive(10))[1] == own
        put(s2, s2.key("operator/separation"), later, block=True)
        assert (await seen2.receive(10))[1] == later  # not `theirs`, which would have come first
        assert seen2.pending == 0 and seen1.pending == 0


def _listening_ports(pid: int) -> list[str]:
    """The local addresses of the TCP sockets process ``pid`` listens on, from /proc."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    out = []
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # LISTEN
                out.append(f[1])
    return out


@pytest.mark.asyncio
async def test_a_peer_listens_on_loopback_only_unless_told() -> None:
    async with await Bus.open(BusConfig(), CELL):
        addrs = _listening_ports(os.getpid())
    assert addrs, "a peer listens somewhere"
    loopback = ("0100007F:",)  # 127.0.0.1, as /proc/net/tcp writes it
    assert all(a.startswith(loopback) for a in addrs), addrs


def test_the_dry_run_prints_every_file_and_no_secret() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "install", "--robot", "192.168.0.10", "--dry-run"],
        capture_output=True,
        text=True,
        check=True,
    )
    out = r.stdout
    for f in (
        "/etc/cadence/cadence.toml",
        "/etc/cadence/credentials/router.json5",
        "cadence-executor.service",
    ):
        assert f in out
    assert 'backend = "ur_rtde"' in out
    assert 'host = "192.168.0.10"' in out
    assert 'source = "polar"' in out
    assert "PRIVATE KEY" not in out
    assert '"password"' not in out
    assert "_base64" not in out
    # every key of every section is in the config: set, or commented at its default
    assert "# fifo_priority = 80" in out
    assert "# window_s = 30.0" in out
    # one ECG source: the strap's gateway here; the operator twin, in its place, for --strap twin
    assert "cadence-ecg_gateway.service" in out
    assert "operator_twin" not in out
    twin = subprocess.run(
        [sys.executable, "-m", "cadence", "install", "--robot", "sim", "--strap", "twin", "--dry-run"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "cadence-operator_twin.service" in twin
    assert "[operator_twin]" in twin
    assert "cadence-ecg_gateway.service" not in twin
    assert "[ecg_gateway]" not in twin


def test_the_install_stages_into_a_folder_as_destdir_does(tmp_path: Path) -> None:
    """`cadence install --root DIR` (issue 56: only --dry-run let one look): every file under DIR at its
    path, naming the real paths inside, the units as the host gets them, each path's mode and owner in
    the manifest for a packager, the cell's CA kept when staged again; nothing outside DIR, and the
    home-folder prefix the units could never see is refused as in a real install."""
    import stat

    def staged(*more: str) -> subprocess.CompletedProcess[str]:
        cmd = ["install", "--robot", "sim", "--strap", "twin", "--root", str(tmp_path / "stage"), *more]
        return subprocess.run([sys.executable, "-m", "cadence", *cmd], capture_output=True, text=True,
                              timeout=120)  # fmt: skip

    etc_before = Path("/etc/cadence").exists()
    r = staged()
    assert r.returncode == 0, r.stderr
    root = tmp_path / "stage"
    unit = (root / "etc/systemd/system/cadence-executor.service").read_text()
    assert "ExecStart=/opt/cadence/.venv/bin/cadence run executor --config /etc/cadence/cadence.toml" in unit
    assert str(root) not in unit
    router = (root / "etc/cadence/credentials/router.json5").read_text()
    assert '"/etc/cadence/credentials/users.txt"' in router  # the real path, not the staged one
    assert stat.S_IMODE((root / "etc/cadence/credentials/cell.json").stat().st_mode) == 0o600
    manifest = json.loads((root / "etc/cadence/installed.json").read_text())
    assert manifest["owners"]["/var/lib/cadence"] == "0750 cadence:cadence"
    assert manifest["owners"]["/etc/cadence/credentials/executor.json5"] == "0640 root:cadence"
    assert "cadence-operator_twin.service" in manifest["units"]
    assert Path("/etc/cadence").exists() == etc_before
    assert "no venv" in r.stdout and "nothing enabled" in r.stdout
    ca = (root / "etc/cadence/credentials/ca.pem").read_text()
    assert staged().returncode == 0
    assert (root / "etc/cadence/credentials/ca.pem").read_text() == ca  # staged again: the same cell
    home = staged("--prefix", "/home/ann/cadence")
    assert home.returncode == 2 and "under a home folder" in home.stderr, home.stderr


def test_scanners_given_to_the_install_turn_monitoring_on_and_the_config_says_so_when_none_is() -> None:
    """`cadence install --scanner NAME:X,Y,YAW:KIND`: the executor's section declares each source, with
    its pose and what it detects, and turns monitoring on; the config decodes as the executor reads it.
    Without one, the section says that monitoring is off and how to turn it on."""
    import tomllib

    import msgspec

    from cadence.deploy.install import config_toml
    from services.executor.settings import Settings as ExecutorSettings
    from services.executor.settings import SourceSettings

    scanners = (
        SourceSettings.parse("scanner:front:1.5,0,180:legs@0.3"),
        SourceSettings.parse("cam:0,2,270:body"),
    )
    opts = Options(robot="sim", strap="twin", scanners=scanners)
    text = config_toml(opts, new_bundle(opts))
    executor = msgspec.convert(tomllib.loads(text)["executor"], ExecutorSettings)
    assert executor.separation
    assert executor.separation_undeclared == "refuse"  # only the declared scanners say where people are
    sensors = executor.sensors()
    assert (sensors["scanner:front"].intrusion_m, sensors["cam"].intrusion_m) == (pytest.approx(1.08), 0.85)
    assert sensors["scanner:front"].pose.x == 1.5
    bare = Options(robot="sim", strap="twin")
    assert "# separation monitoring is off: no --scanner was given" in config_toml(bare, new_bundle(bare))


def test_a_joining_host_gets_its_own_certificates_from_the_same_ca(tmp_path: Path) -> None:
    first = new_bundle(Options(robot="sim", router_host="cellpc"))
    (tmp_path / "cell.json").write_text(first.to_json())
    joined = Bundle.load(tmp_path / "cell.json")
    assert joined == first
    p = plan(Options(robot="sim", services=("pareto_store",), join=tmp_path / "cell.json"), joined)
    names = {f.path.name for f in p.files}
    assert "pareto_store.json5" in names
    assert "router.json5" not in names
    assert "executor.json5" not in names
    cfg = json.loads(next(f for f in p.files if f.path.name == "pareto_store.json5").text.split("\n", 1)[1])
    assert cfg["connect"]["endpoints"] == ["tls/cellpc:7447"]
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(Exception, match=r"bad\.json: not a cell bundle"):
        Bundle.load(tmp_path / "bad.json")
    other = json.loads(first.to_json()) | {"ca_key": make_ca("c2").key.decode()}  # another CA's key
    (tmp_path / "mixed.json").write_text(json.dumps(other))
    with pytest.raises(Exception, match=r"mixed\.json: not a cell bundle.*not the CA certificate's"):
        Bundle.load(tmp_path / "mixed.json")


CHILD = """
import os, sys, time
from common.runtime.lifetime import die_with_parent
parent = os.getpid()
if os.fork() == 0:  # the child: once it has asked to die with its parent, it says its pid
    die_with_parent(parent)
    print(os.getpid(), flush=True)
    time.sleep(120)
    os._exit(0)
time.sleep(120)
"""


def test_a_child_dies_with_its_parent_even_on_sigkill() -> None:
    parent = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True, cwd=REPO)
    assert parent.stdout is not None
    child = int(parent.stdout.readline())
    parent.send_signal(signal.SIGKILL)
    parent.wait(10)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:  # gone, or a zombie not yet reaped by init: dead either way
            if Path(f"/proc/{child}/stat").read_text().split(")")[-1].split()[0] == "Z":
                break
        except FileNotFoundError:
            break
        time.sleep(0.05)
    else:
        os.kill(child, signal.SIGKILL)
        raise AssertionError("the child outlived its SIGKILLed parent")


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--services", "executor,planner"], "--services: unknown ['planner']"),
        (["--join", "/nonexistent/cell.json"], "/nonexistent/cell.json: (file)"),
        (["--cell", "cell 1/x"], "--cell 'cell 1/x': letters, digits"),
        (["--robot", "ur16 e"], "--robot 'ur16 e': a host name"),
        (["--strap", "twin", "--services", "ecg_gateway"], "--services ecg_gateway: with --strap twin"),
        (["--scanner", "front:1.5,0:legs"], "--scanner 'front:1.5,0:legs'"),
        (["--scanner", "front:1.5,0,0:feet"], "--scanner 'front:1.5,0,0:feet'"),
        (["--prefix", "/root/cadence"], "--prefix /root/cadence: under a home folder, which the units"),
        (["--prefix", "/home/ann/../ann/cadence"], "under a home folder"),
    ],
)
def test_a_bad_install_request_is_one_line_and_exit_2(args: list[str], said: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "cadence", "install", "--robot", "sim", "--dry-run", *args],
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 2, r.stderr
    assert said in r.stderr, r.stderr


def test_an_install_on_a_host_without_systemd_stops_before_it_writes_anything(tmp_path: Path) -> None:
    """It failed at `systemctl daemon-reload`, after all of /etc/cadence and a 626 MB venv (issue 43)."""
    from cadence.deploy.install import InstallError, install, no_systemd

    fake = tmp_path / "root"
    (fake / "proc/1").mkdir(parents=True)
    (fake / "proc/1/comm").write_text("bash\n")
    assert no_systemd(fake) == "this host does not run systemd (PID 1 is bash)"
    if not no_systemd() or os.geteuid() != 0:
        pytest.skip("this host runs systemd (an install here would write /etc), or this is not root")
    before = Path("/etc/cadence").exists()
    with pytest.raises(InstallError, match=r"does not run systemd .*nothing was written.*--no-systemctl"):
        install(Options(robot="sim", strap="twin", prefix=tmp_path / "opt"))
    assert Path("/etc/cadence").exists() == before
    assert not (tmp_path / "opt").exists()


POUR = """
import asyncio, sys
from common.runtime.bus import Bus, BusConfig
async def pour(config, cell, suffix):
    async with await Bus.open(BusConfig(config_file=config), cell) as bus:
        while True:
            bus.put_raw(bus.key(suffix), bytes(100_000), True)
            await asyncio.sleep(0.02)
asyncio.run(pour(*sys.argv[1:]))
"""  # a service of the cell that connects and sends much (5 MB/s at block QoS, as a plant's reads are)


@pytest.mark.asyncio
async def test_services_that_connect_and_send_much_hold_up_no_separation_in_the_cell(tmp_path: Path) -> None:
    """The cell's router, as `cadence router` runs it, goes on carrying the separation while two services
    connect and put 100 kB messages at block QoS. A restarting service, `cadence top` or a plant's link
    connects at any time. A router that runs every task on one thread (Zenoh's ``ZENOH_RUNTIME`` with
    each pool handed over to ``app``: a quarter less CPU under `cadence bench plant`) stopped routing
    for 5 s at such a moment, the separation with it, and the arm would have held: this fails that way."""
    ca = make_ca(CELL)
    passwords = {a: f"pw-{a}" for a in ACCOUNTS}
    own = f"tls/127.0.0.1:{free_port()}"
    router_file = cell_router(tmp_path, ca, passwords, [own]).config_file
    account = {a: account_file(tmp_path, ca, CELL, a, passwords[a], [own]) for a in ACCOUNTS}
    run = [sys.executable, "-m", "cadence", "router", "--zenoh-config", str(router_file)]
    procs = [subprocess.Popen(run, stderr=subprocess.PIPE, text=True)]
    try:
        assert procs[0].stderr is not None and "listening" in procs[0].stderr.readline()
        async with (
            await Bus.open(account["separation_sensor"], CELL) as sensor,
            await Bus.open(account["monitor"], CELL) as monitor,
        ):
            came: list[float] = []  # when each separation came to the cell's monitor
            poured: list[str] = []
            seps = monitor.key("operator/separation")
            monitor.subscribe_raw(seps, lambda *_: came.append(time.monotonic()))
            for suffix in ("robot/cycle", "hrv/window"):
                monitor.subscribe_raw(monitor.key(suffix), lambda key, _: poured.append(key))
            await sensor.until_subscribed(seps, 30)
            t0, seq = time.monotonic(), 0
            for name, suffix in (("executor", "robot/cycle"), ("hrv_analyser", "hrv/window")):
                pour = [sys.executable, "-c", POUR, str(account[name].config_file), CELL, suffix]
                procs.append(subprocess.Popen(pour))
            while time.monotonic() < t0 + 8.0:  # they start, connect and send meanwhile
                put(
                    sensor,
                    seps,
                    Separation(t_ns=time.time_ns(), seq=seq, distance_m=2.0, source="scanner:front"),
                )
                seq += 1
                await asyncio.sleep(0.05)
            came.append(time.monotonic())  # a separation that never came after the last one counts too
        assert len(set(poured)) == 2  # both services were on the bus and sent
        gaps = [b - a for a, b in itertools.pairwise(came)]
        assert len(came) > 100 and max(gaps) < 1.0, max(gaps)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait(10)
