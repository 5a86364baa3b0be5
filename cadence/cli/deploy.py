"""`cadence install` and `cadence uninstall`: a robot cell under systemd (cadence/deploy/install.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cadence.cli._common import Commands, arg, positive_int
from schemas.topology import DEFAULT_CELL
from services.registry import IN_GRAPH

cli = Commands()


@cli.command(
    "install",
    help="install this host's part of a robot cell under systemd (root)",
    description="Creates the cadence user, /etc/cadence/cadence.toml (every key, commented), one bus "
    "account per service (random password, its own certificate from the cell's CA), the router's "
    "mTLS config with the ACL generated from the topology, a Python the service user can run and the "
    "venv on it under the prefix, and installs and enables the units. Re-running keeps the config, "
    "the CA and the passwords.",
)
@arg("--robot", required=True, metavar="HOST|sim", help="the UR controller's address, or sim")
@arg(
    "--strap",
    default="Polar H10",
    metavar="ADDRESS|NAME|twin|replay",
    help="the Polar H10 (MAC address or part of its name; default 'Polar H10'), or twin/replay",
)
@arg("--cell", default=DEFAULT_CELL, help=f"the cell's name (default {DEFAULT_CELL})")
@arg("--prefix", default="/opt/cadence", help="where the venv and Python go (default /opt/cadence)")
@arg(
    "--services",
    default="",
    help=f"what runs on this host, comma-separated, of {', '.join((*(s.name for s in IN_GRAPH), 'router'))} "
    "(default: the whole cell and its router, its ECG from the operator twin for --strap twin, else from "
    "the gateway)",
)
@arg("--router-host", default="", help="where other hosts reach the router (default: hostname)")
@arg("--port", type=positive_int(1), default=7447, help="the router's TLS port (default 7447)")
@arg("--join", metavar="CELL.json", help="the first host's /etc/cadence/credentials/cell.json")
@arg("--python", metavar="PATH", help="the interpreter for the venv (default: see docs/operations.md)")
@arg("--from", dest="source", metavar="SPEC", help="what to install (default: this checkout)")
@arg("--no-venv", action="store_true", help="files and units only")
@arg("--no-systemctl", action="store_true", help="no daemon-reload or enable")
@arg("--dry-run", action="store_true", help="print every file it would write, and stop")
@arg(
    "--plant",
    metavar="plant.json",
    help="let a plant's router read this cell (the file `cadence plant-router` writes): the router trusts "
    "the plant's CA beside the cell's; nothing from the plant may publish, answer or ask",
)
@arg(
    "--uplink-interface",
    metavar="IFACE",
    help="with --plant: the network interface the plant's router reaches this cell's on (e.g. eth1); "
    "the arm's state leaves on it at 5 Hz, as the plant takes it. No host of the cell may reach the "
    "router over it",
)
@arg(
    "--root",
    metavar="DIR",
    help="stage the install into DIR (as DESTDIR does: DIR/etc/cadence/…, DIR/etc/systemd/system/…, naming "
    "the real paths inside) to inspect or package it; no user, venv or systemctl, no root needed",
)
@arg(
    "--scanner",
    action="append",
    default=[],
    metavar="NAME:POSE:KIND[,OPTION=V]",
    help="a separation source (repeat for each): its pose in the cell frame (X,Y,YAW; X,Y,Z,YAW; or "
    "X,Y,Z,ROLL,PITCH,YAW, m and degrees: a ceiling camera looking down has a pitch of 90) and what it "
    "detects (hand, arm, body, legs, legs@HEIGHT_M, beam: a single beam), with the options resolution=MM, "
    "height=M and c=M (a C of its own), e.g. scanner:front:1.5,0,180:legs@0.3 or "
    "cam:top:0,0,3,0,90,0:hand,resolution=14. Checked as the executor checks it at start (ISO 13855's C; "
    "a hand sensor needs its resolution). Given, the executor's separation monitoring is on, requires "
    "each, and takes no other; each gets its own bus account (sensor_<name>)",
)
def cmd_install(args: argparse.Namespace) -> int:
    from cadence.deploy.install import Options, install
    from common.runtime.errors import InputError
    from services.executor.settings import SourceSettings

    try:
        scanners = tuple(SourceSettings.parse(s) for s in args.scanner)
    except ValueError as exc:
        raise InputError(f"--scanner {exc}") from None
    if args.uplink_interface and not args.plant:
        raise InputError("--uplink-interface is the plant's way in: give --plant plant.json with it")

    opts = Options(
        robot=args.robot,
        strap=args.strap,
        cell_name=args.cell,
        prefix=Path(args.prefix),
        services=tuple(s.strip() for s in args.services.split(",") if s.strip()),
        router_host=args.router_host,
        port=args.port,
        join=Path(args.join) if args.join else None,
        python=args.python,
        source=args.source,
        venv=not args.no_venv,
        systemctl=not args.no_systemctl,
        scanners=scanners,
        root=Path(args.root).absolute() if args.root else None,
        plant=Path(args.plant) if args.plant else None,
        uplink=args.uplink_interface or None,
    )
    for line in install(opts, dry_run=args.dry_run):
        print(line)
    return 0


@cli.command("uninstall", help="remove what `cadence install` wrote (keeps /var/lib/cadence, the data)")
@arg("--keep-venv", action="store_true", help="leave the venv and Python under the prefix")
def cmd_uninstall(args: argparse.Namespace) -> int:
    from cadence.deploy.install import uninstall

    for line in uninstall(keep_venv=args.keep_venv):
        print(line)
    return 0


@cli.command(
    "plant-router",
    help="write a plant router's files: its config, its monitor's account, and plant.json for the cells",
    description="Writes into OUT: router.json5 (the plant's router: it connects to every cell's router as "
    "'plant' over mTLS, takes each cell's arm state at 5 Hz, lets its monitor read every cell and say "
    "nothing), users.txt, plant-monitor.json5 (`cadence plant --zenoh-config`), plant-secret.json (its "
    "CA and password, kept when run again) and plant.json, which every cell's install takes with "
    "`cadence install --plant plant.json`. Run `zenohd -c OUT/router.json5` (or `cadence router "
    "--zenoh-config`) on the plant's host. With --line, each line's router (OUT/LINE/router.json5, on the "
    "line's host) reads its cells the same way and the plant's router reads the lines.",
)
@arg(
    "--cell",
    action="append",
    required=True,
    metavar="NAME=ENDPOINT=CA.pem[=LINE]",
    help="a cell: its name, its router's endpoint, its CA certificate (the cell's "
    "/etc/cadence/credentials/ca.pem), and the line whose router reads it (then every cell names one)",
)
@arg(
    "--line",
    action="append",
    default=[],
    metavar="NAME=ENDPOINT",
    help="a line: where its router listens for the plant's; its files go in OUT/NAME/ (router.json5, "
    "users.txt), and the plant's router reads the lines, not the cells",
)
@arg(
    "--listen",
    default="tls/0.0.0.0:7448",
    help="where the plant's monitors connect (default tls/0.0.0.0:7448)",
)
@arg("--host", action="append", default=[], help="the plant router's host names (default: this host's name)")
@arg("--out", required=True, metavar="DIR")
def cmd_plant_router(args: argparse.Namespace) -> int:
    import socket

    from cadence.deploy.plant import load_secret, new_secret, parse_cell, parse_line, plant_files
    from common.runtime.errors import InputError
    from common.runtime.storage import atomic_write

    out = Path(args.out).absolute()
    cells: dict[str, tuple[str, bytes]] = {}
    lines: dict[str, tuple[str, list[str]]] = {n: (e, []) for n, e in map(parse_line, args.line)}
    for spec in args.cell:
        name, endpoint, ca, line = parse_cell(spec)
        if bool(line) != bool(lines) or (line and line not in lines):
            named = ", ".join(lines)
            raise InputError(
                f"--cell {spec}: with --line, every cell names one ({named}); without, none does"
            )
        try:
            cells[name] = (endpoint, ca.read_bytes())
        except OSError as exc:
            raise InputError(f"--cell {spec}: {ca}: {exc.strerror or exc}") from None
        if line:
            lines[line][1].append(name)
    secret_file = out / "plant-secret.json"
    secret = load_secret(secret_file) if secret_file.exists() else new_secret()
    files = plant_files(secret, cells, args.listen, args.host or [socket.gethostname()], out, lines)
    for name, (text, mode) in files.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        atomic_write(out / name, text.encode(), mode)
        print(f"wrote {out / name} ({mode:o})")
    print(f"give {out / 'plant.json'} to each cell: cadence install … --plant plant.json")
    return 0
