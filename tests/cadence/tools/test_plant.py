"""`cadence plant` (issue 58): every cell on the mesh in one table. The aggregator keeps each cell's
statuses, robot, selection and window with their ages, and says which service of which cell went quiet;
the command reads two cells on one bus."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from rich.console import Console

from cadence.tools.plant import Plant, plant_watch
from common.runtime.bus import Bus, BusConfig
from schemas import HrvWindow, RobotState, Selection, Separation, ServiceStatus
from schemas.topology import SERVICES, encode
from tests.support.cell import account_file, config_file, free_port, put


def json5_of(path: Path) -> dict:
    """A config as `cadence` writes it: comment lines, then JSON."""
    return json.loads(
        "".join(line for line in path.read_text().splitlines(True) if not line.startswith("//"))
    )


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


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="threads' nice values are read in /proc")
@pytest.mark.parametrize("before", [0, 15])
def test_the_plants_processes_yield_to_a_cells_every_thread_of_them(before: int) -> None:
    """`cadence plant` and `cadence record --plant` take the plant's priority: every thread, the ones a
    library started before (numpy's BLAS does on import) and the ones started after; a process already
    nicer keeps its own."""
    script = f"""
import os, threading
from cadence.tools.plant import yield_to_cells
os.nice({before})
stop = threading.Event()
early = threading.Thread(target=stop.wait); early.start()
yield_to_cells()
late = threading.Thread(target=stop.wait); late.start()
print(sorted({{int(open(f"/proc/self/task/{{t}}/stat").read().rsplit(")", 1)[1].split()[16])
              for t in os.listdir("/proc/self/task")}}))
stop.set()
"""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout) == [max(before, 10)]


@pytest.mark.asyncio
async def test_cadence_plant_shows_two_cells_on_one_bus() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    async with await Bus.open(BusConfig(listen=[endpoint]), "pc1") as bus:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cadence", "plant", "--connect", endpoint, "--once", "10",
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


async def plant_reads_each_downsampled(watcher: Bus, executors: dict[str, Bus]) -> None:
    """Each cell puts its arm's state at 50 Hz for 3 s: the plant's monitor gets every cell's, and none
    above ``UPLINK_STATE_HZ`` (each cell its own budget). First each sends until the plant has one of it:
    a cell's clients are not told of a plant's wildcard subscription, so a publisher cannot wait for it."""
    from cadence.deploy.cell import UPLINK_STATE_HZ

    state = RobotState(t_ns=1, seq=0, q=[0.0] * 6, qd=[0.0] * 6, tcp=[0.0] * 6)
    got = dict.fromkeys(executors, 0)

    def came(key: str, _: bytes) -> None:
        got[key.split("/")[1]] += 1

    def put_each() -> None:
        for ex in executors.values():
            put(ex, ex.key("robot/state"), state)

    watcher.subscribe_raw("cadence/*/robot/state", came)
    async with asyncio.timeout(60):
        while not all(got.values()):
            put_each()
            await asyncio.sleep(0.02)
    got = dict.fromkeys(executors, 0)
    t0 = asyncio.get_running_loop().time()
    for _ in range(150):  # 3 s at 50 Hz from each cell
        put_each()
        await asyncio.sleep(0.02)
    span = asyncio.get_running_loop().time() - t0
    async with asyncio.timeout(10):
        while not all(got.values()):
            await asyncio.sleep(0.05)
    for cell, n in got.items():
        assert 1 <= n <= UPLINK_STATE_HZ * span + 2, (cell, n, span)


async def the_plant_side_cannot_act_on_the_cell(plant_side: Bus, m1: Bus, s1: Bus) -> None:
    """A plant router that allows anything (``plant_side``, its own session) puts a far distance and a
    selection into the cell of ``m1`` (its monitor) and ``s1`` (its separation sensor), and asks it to
    resume: none of it arrives, no resume is answered. A liveliness query's round trip over the plant's
    link before and after says the link is up and that what was sent before it has been handled."""
    cell = m1.cell
    seps = m1.subscribe(m1.key("operator/separation"), Separation)
    sels = m1.subscribe(m1.key("decision/selection"), Selection)
    await s1.until_subscribed(s1.key("operator/separation"), 30)
    token = s1.transport.session.liveliness().declare_token(f"cadence/{cell}/health/separation_sensor")

    async def round_trip() -> bool:
        get, key = plant_side.transport.session.liveliness().get, f"cadence/{cell}/health/**"
        return bool(await asyncio.to_thread(lambda: list(get(key, timeout=2.0))))

    async with asyncio.timeout(60):  # the plant's link is up (or the puts below would prove nothing)
        while not await round_trip():
            pass
    far = Separation(t_ns=3, seq=0, distance_m=100.0, source="scanner:front")
    put(plant_side, f"cadence/{cell}/operator/separation", far, block=True)
    put(plant_side, f"cadence/{cell}/decision/selection",
        Selection(t_ns=3, seq=9, k=15, n=15, delta=0, reason="initial"), block=True)  # fmt: skip
    resumed = await asyncio.to_thread(
        lambda: list(plant_side.transport.session.get(f"cadence/{cell}/robot/resume", timeout=2.0))
    )
    assert await round_trip()
    near = Separation(t_ns=4, seq=1, distance_m=0.6, source="scanner:front")
    put(s1, s1.key("operator/separation"), near, block=True)
    assert (await seps.receive(10))[1] == near  # the first: the plant's 100 m never came
    assert sels.pending == 0
    assert all(r.err is not None for r in resumed)  # no answer, or a refusal
    token.undeclare()


@pytest.mark.asyncio
async def test_a_plant_router_reads_each_cell_downsampled_and_cannot_act_on_one(tmp_path: Path) -> None:
    """Two cells, each behind its own router over mTLS, and a plant router that connects to both (issue
    58; one plant CA here): the plant's monitor reads both cells at once, the arm's state of each at no
    more than 5 Hz though the cells send 50; it may say nothing. And a plant router that allows anything
    (compromised, or misconfigured) still cannot put a distance or a selection into a cell, nor ask it to
    resume: the cell's own router lets in nothing from the plant's link."""
    from cadence.deploy.cell import (
        ACCOUNTS,
        PLANT,
        PLANT_MONITOR,
        Tls,
        identity,
        router_config,
        users_file,
    )
    from cadence.deploy.pki import issue, make_ca
    from cadence.deploy.plant import new_secret, plant_files

    # each cell its own CA, the plant its own; the plant's files as `cadence plant-router` writes them
    cells = {c: f"tls/127.0.0.1:{free_port()}" for c in ("c1", "c2")}
    cas = {c: make_ca(c) for c in cells}
    secret = new_secret()
    plant_at = f"tls/127.0.0.1:{free_port()}"
    for name, (text, _) in plant_files(secret, {c: (e, cas[c].cert) for c, e in cells.items()}, plant_at,
                                       ["127.0.0.1"], tmp_path).items():  # fmt: skip
        (tmp_path / name).write_text(text)
    routers: list[BusConfig] = []
    for c, endpoint in cells.items():
        passwords = users_file(c, {a: f"pw-{a}" for a in ACCOUNTS})
        (tmp_path / f"{c}.users").write_text(passwords + f"{PLANT}:{secret.password}\n")
        leaf = issue(cas[c], identity(c, "router"), c, ["127.0.0.1"])
        tls = Tls(cas[c].cert + secret.ca.cert, leaf.cert, leaf.key)  # the plant's CA beside the cell's
        cfg = router_config(c, [endpoint], tls, str(tmp_path / f"{c}.users"), plant=True)
        routers.append(config_file(tmp_path, f"{c}-router", cfg))
    plant_cfg = json5_of(tmp_path / "router.json5")
    plant = config_file(tmp_path, "plant", plant_cfg)
    rogue_cfg = {**plant_cfg, "access_control": {"enabled": False}, "downsampling": [],
                 "listen": {"endpoints": [f"tls/127.0.0.1:{free_port()}"]}}  # fmt: skip
    rogue = config_file(tmp_path, "rogue", rogue_cfg)
    # the plant's monitor may read and receive, and do nothing else: no rule of its lets it put or ask
    acl = plant_cfg["access_control"]
    mine = {r for p in acl["policies"] if PLANT_MONITOR in p["subjects"] for r in p["rules"]}
    assert {m for r in acl["rules"] if r["id"] in mine for m in r["messages"]} <= {
        "declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "put", "delete", "reply",
        "liveliness_token"}  # fmt: skip
    assert all(r["flows"] == ["egress"] for r in acl["rules"] if r["id"] in mine and "put" in r["messages"])

    def account(cell: str, name: str, at: str) -> BusConfig:
        return account_file(tmp_path, cas[cell], cell, name, f"pw-{name}", [at])

    monitor_cfg = json5_of(tmp_path / "plant-monitor.json5")
    async with (
        await Bus.open(routers[0], "c1"),
        await Bus.open(routers[1], "c2"),
        await Bus.open(account("c1", "executor", cells["c1"]), "c1") as ex1,
        await Bus.open(account("c2", "executor", cells["c2"]), "c2") as ex2,
        await Bus.open(plant, "plant"),
        await Bus.open(config_file(tmp_path, "monitor", monitor_cfg), "plant") as watcher,
    ):
        await plant_reads_each_downsampled(watcher, {"c1": ex1, "c2": ex2})
    # a plant router that lets anything through: the cells' routers still let nothing in from it
    async with (
        await Bus.open(routers[0], "c1"),
        await Bus.open(account("c1", "monitor", cells["c1"]), "c1") as m1,
        await Bus.open(account("c1", "separation_sensor", cells["c1"]), "c1") as s1,
        await Bus.open(rogue, "plant") as plant_side,
    ):
        await the_plant_side_cannot_act_on_the_cell(plant_side, m1, s1)


@pytest.mark.asyncio
async def test_a_cells_router_sends_the_plant_its_arm_state_at_5_hz_on_the_uplink_and_the_cell_all_of_it(
    tmp_path: Path,
) -> None:
    """`cadence install --plant … --uplink-interface IFACE`: the cell's router takes the plant's link on
    this host's network interface and downsamples the arm's state there, as it leaves; the cell's own
    sessions, on loopback, get every message. The plant's side here downsamples nothing itself (a plant
    router with no rules at all): what it gets at 5 Hz is the cell's doing."""
    from cadence.bench.plant import host_interface
    from cadence.deploy.cell import ACCOUNTS, PLANT, Tls, identity, router_config, users_file
    from cadence.deploy.pki import issue, make_ca
    from cadence.deploy.plant import new_secret, plant_files

    nic = host_interface()
    if nic is None:
        pytest.skip("this host has no network interface with an IPv4 address but loopback")
    iface, address = nic
    ca, secret = make_ca("c1"), new_secret()
    own, up = f"tls/127.0.0.1:{free_port()}", f"tls/{address}:{free_port()}"
    for name, (text, _) in plant_files(secret, {"c1": (up, ca.cert)}, f"tls/127.0.0.1:{free_port()}",
                                       ["127.0.0.1"], tmp_path).items():  # fmt: skip
        (tmp_path / name).write_text(text)
    (tmp_path / "c1.users").write_text(
        users_file("c1", {a: f"pw-{a}" for a in ACCOUNTS}) + f"{PLANT}:{secret.password}\n"
    )
    leaf = issue(ca, identity("c1", "router"), "c1", ["127.0.0.1", address])
    tls = Tls(ca.cert + secret.ca.cert, leaf.cert, leaf.key)
    cfg = router_config("c1", [own, up], tls, str(tmp_path / "c1.users"), plant=True, uplink=iface)
    plain = {**json5_of(tmp_path / "router.json5"), "access_control": {"enabled": False}, "downsampling": []}

    def account(name: str) -> BusConfig:
        return account_file(tmp_path, ca, "c1", name, f"pw-{name}", [own])

    async with (
        await Bus.open(config_file(tmp_path, "c1-router", cfg), "c1"),
        await Bus.open(account("executor"), "c1") as ex1,
        await Bus.open(account("monitor"), "c1") as m1,
        await Bus.open(config_file(tmp_path, "plain", plain), "plant") as plant_side,
    ):
        in_cell = []
        m1.subscribe_raw(m1.key("robot/state"), lambda key, _: in_cell.append(key))
        await ex1.until_subscribed(ex1.key("robot/state"), 30)
        await plant_reads_each_downsampled(plant_side, {"c1": ex1})
        # 3 s at 50 Hz and what went before the plant had one: all of it (a drop or two aside), not 15
        assert len(in_cell) >= 140


def test_plant_router_writes_the_plants_files_and_a_cells_install_takes_plant_json(tmp_path: Path) -> None:
    """`cadence plant-router` and `cadence install --plant` (issue 58): the plant's router trusts the plant's
    and every cell's CA, connects to each cell and downsamples each; plant.json holds no key; run again,
    the plant's CA is kept. A cell staged with it lets the plant in as the rules above say, trusting the
    plant's CA beside its own, and sends the arm's state on its uplink's interface at the plant's rate. A
    bad --cell, a plant secret given for plant.json and an uplink without a plant are one line each."""
    from cadence.deploy.pki import make_ca

    def cadence(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "cadence", *args], capture_output=True, text=True,
                              timeout=120)  # fmt: skip

    cas = {}
    for c in ("c1", "c2"):
        cas[c] = make_ca(c).cert
        (tmp_path / f"{c}.pem").write_bytes(cas[c])
    out = tmp_path / "plant"
    specs = [f"--cell={c}=tls/10.0.{i}.5:7447={tmp_path / f'{c}.pem'}" for i, c in enumerate(cas, 1)]
    r = cadence("plant-router", *specs, "--out", str(out), "--host", "plant.local")
    assert r.returncode == 0, r.stderr
    router = json5_of(out / "router.json5")
    assert router["connect"]["endpoints"] == ["tls/10.0.1.5:7447", "tls/10.0.2.5:7447"]
    assert [d["rules"][0]["key_expr"] for d in router["downsampling"]] == [
        "cadence/c1/robot/state", "cadence/c2/robot/state"]  # fmt: skip
    import base64

    trusted = base64.b64decode(router["transport"]["link"]["tls"]["root_ca_certificate_base64"])
    assert cas["c1"] in trusted and cas["c2"] in trusted and trusted.count(b"BEGIN CERTIFICATE") == 3
    given = json.loads((out / "plant.json").read_text())
    assert set(given) == {"ca_cert", "password"}
    assert (out / "plant-secret.json").stat().st_mode & 0o077 == 0
    assert cadence("plant-router", *specs, "--out", str(out)).returncode == 0
    assert json.loads((out / "plant.json").read_text()) == given  # run again: the same plant

    stage = tmp_path / "stage"
    r = cadence("install", "--robot", "sim", "--strap", "twin", "--cell", "c1", "--root", str(stage),
                "--plant", str(out / "plant.json"), "--uplink-interface", "eth1")  # fmt: skip
    assert r.returncode == 0, r.stderr
    creds = stage / "etc/cadence/credentials"
    assert f"plant:{given['password']}" in (creds / "users.txt").read_text().splitlines()
    cell_router = json5_of(creds / "router.json5")
    assert "c1: plant reads" in {rule["id"] for rule in cell_router["access_control"]["rules"]}
    cell_trusts = base64.b64decode(cell_router["transport"]["link"]["tls"]["root_ca_certificate_base64"])
    assert given["ca_cert"].encode() in cell_trusts
    (up,) = cell_router["downsampling"]  # the arm's state leaves on the uplink under the line's cap
    assert up["interfaces"] == ["eth1"] and up["flows"] == ["egress"]
    assert up["rules"] == [{"key_expr": "cadence/c1/robot/state", "freq": 4.5}]

    bad = cadence("plant-router", "--cell", "c1=tls/10.0.1.5:7447", "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "expected NAME=ENDPOINT=CA.pem" in bad.stderr, bad.stderr
    wrong = cadence("install", "--robot", "sim", "--strap", "twin", "--root", str(tmp_path / "s2"),
                    "--plant", str(out / "plant-secret.json"))  # fmt: skip
    assert wrong.returncode == 2 and "not a plant.json" in wrong.stderr, wrong.stderr
    alone = cadence("install", "--robot", "sim", "--root", str(tmp_path / "s3"), "--uplink-interface", "eth1")
    assert alone.returncode == 2 and "give --plant plant.json with it" in alone.stderr, alone.stderr


@pytest.mark.asyncio
async def test_a_line_router_between_cells_and_the_plant_passes_reading_up_and_nothing_down(
    tmp_path: Path,
) -> None:
    """Cells behind a line router, the line behind the plant's router, as `cadence bench plant` lays
    them out (each cell its own CA, the plant's CA for the line and the plant): the plant monitor reads
    both cells through two hops, the arm's state of each at no more than 5 Hz. A plant router that
    allows anything, on the line's uplink, can put no distance or selection into a cell and get no
    resume, even into a cell whose own router would let it: the line lets nothing in from its uplink but
    reading."""
    from cadence.bench.plant import layout

    lay = layout(tmp_path, 2, per_line=2)
    (c1, c2), (line,) = lay.cells, lay.line_routers
    cfg = lambda path: BusConfig(config_file=str(path))  # noqa: E731
    plant_cfg = json5_of(lay.plant_router.config)
    rogue_cfg = {**plant_cfg, "access_control": {"enabled": False}, "downsampling": [],
                 "listen": {"endpoints": [f"tls/127.0.0.1:{free_port()}"]}}  # fmt: skip
    async with (
        await Bus.open(cfg(lay.cell_routers[0].config), c1.name),
        await Bus.open(cfg(lay.cell_routers[1].config), c2.name),
        await Bus.open(cfg(line.config), "line1"),
        await Bus.open(cfg(lay.plant_router.config), "plant"),
        await Bus.open(cfg(c1.accounts["executor"]), c1.name) as ex1,
        await Bus.open(cfg(c2.accounts["executor"]), c2.name) as ex2,
        await Bus.open(cfg(lay.monitor), "plant") as watcher,
    ):
        await plant_reads_each_downsampled(watcher, {c1.name: ex1, c2.name: ex2})
    # the cell's own router refuses the plant too (above); here it lets anything in, so what is proven
    # is the line's own refusal
    open_cell = {**json5_of(lay.cell_routers[0].config), "access_control": {"enabled": False}}
    async with (
        await Bus.open(config_file(tmp_path, "open-cell", open_cell), c1.name),
        await Bus.open(cfg(line.config), "line1"),
        await Bus.open(cfg(c1.reader), c1.name) as m1,
        await Bus.open(cfg(c1.accounts["separation_sensor"]), c1.name) as s1,
        await Bus.open(config_file(tmp_path, "rogue", rogue_cfg), "plant") as plant_side,
    ):
        await the_plant_side_cannot_act_on_the_cell(plant_side, m1, s1)


def test_plant_router_with_lines_writes_each_lines_router_and_the_plant_reads_the_lines(
    tmp_path: Path,
) -> None:
    """`cadence plant-router --line`: each line's router reads its own cells (trusting their CAs and the
    plant's) and lets the plant read it; the plant's router connects to the lines only, each line's link
    bringing its own cells' keys. A cell that names no line, with lines given, is one line and exit 2."""
    from cadence.deploy.cell import PLANT, identity
    from cadence.deploy.pki import make_ca

    for c in ("c1", "c2", "c3"):
        (tmp_path / f"{c}.pem").write_bytes(make_ca(c).cert)
    cells = [f"--cell=c1=tls/10.0.1.5:7447={tmp_path / 'c1.pem'}=l1",
             f"--cell=c2=tls/10.0.1.6:7447={tmp_path / 'c2.pem'}=l1",
             f"--cell=c3=tls/10.0.2.5:7447={tmp_path / 'c3.pem'}=l2"]  # fmt: skip
    lines = ["--line", "l1=tls/10.0.1.2:7448", "--line", "l2=tls/10.0.2.2:7448"]
    out = tmp_path / "plant"
    run = [sys.executable, "-m", "cadence", "plant-router", *cells, *lines, "--out", str(out)]
    r = subprocess.run(run, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    l1 = json5_of(out / "l1" / "router.json5")
    assert l1["connect"]["endpoints"] == ["tls/10.0.1.5:7447", "tls/10.0.1.6:7447"]
    assert l1["listen"]["endpoints"] == ["tls/10.0.1.2:7448"]
    readers = {s["id"] for s in l1["access_control"]["subjects"] if "usernames" in s}
    assert PLANT in readers  # the plant's uplink, read-only as a monitor
    assert (out / "l1" / "users.txt").read_text().startswith(f"{PLANT}:")
    capped = [(d["rules"][0]["key_expr"], d["rules"][0]["freq"]) for d in l1["downsampling"]]
    assert capped == [("cadence/c1/robot/state", 5.0), ("cadence/c2/robot/state", 5.0)]
    plant = json5_of(out / "router.json5")
    assert plant["downsampling"] == []  # the lines capped their cells: a second cap drops what came early
    assert plant["connect"]["endpoints"] == ["tls/10.0.1.2:7448", "tls/10.0.2.2:7448"]
    ups = {r["id"]: r["key_exprs"] for r in plant["access_control"]["rules"] if r["id"].endswith(": up")}
    assert ups == {"l1: up": ["cadence/c1/**", "cadence/c2/**"], "l2: up": ["cadence/c3/**"]}
    known = {s["id"]: s["cert_common_names"] for s in plant["access_control"]["subjects"]}
    assert known["l1"] == [identity("l1", "router")]
    bad = subprocess.run([*run[:-2], f"--cell=c4=tls/10.0.3.5:7447={tmp_path / 'c1.pem'}", "--out",
                          str(tmp_path / "x")], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert bad.returncode == 2 and "every cell names one" in bad.stderr, bad.stderr
