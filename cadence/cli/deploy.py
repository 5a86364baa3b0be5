"""`cadence install` and `cadence uninstall`: a robot cell under systemd (the work: cadence/install.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cadence.cli._common import positive_int
from schemas.topology import DEFAULT_CELL
from schemas.topology import SERVICES as GRAPH_SERVICES


def cmd_install(args: argparse.Namespace) -> int:
    from cadence.install import Options, install

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
    )
    for line in install(opts, dry_run=args.dry_run):
        print(line)
    return 0


def cmd_uninstall(args: argparse.Namespace) -> int:
    from cadence.install import uninstall

    for line in uninstall(keep_venv=args.keep_venv):
        print(line)
    return 0


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    inst = sub.add_parser(
        "install",
        help="install this host's part of a robot cell under systemd (root)",
        description="Creates the cadence user, /etc/cadence/cadence.toml (every key, commented), one bus "
        "account per service (random password, its own certificate from the cell's CA), the router's "
        "mTLS config with the ACL generated from the topology, a Python the service user can run and the "
        "venv on it under the prefix, and installs and enables the units. Re-running keeps the config, "
        "the CA and the passwords.",
    )
    inst.add_argument(
        "--robot", required=True, metavar="HOST|sim", help="the UR controller's address, or sim"
    )
    inst.add_argument(
        "--strap",
        default="Polar H10",
        metavar="ADDRESS|NAME|twin|replay",
        help="the Polar H10 (MAC address or part of its name; default 'Polar H10'), or twin/replay",
    )
    inst.add_argument("--cell", default=DEFAULT_CELL, help=f"the cell's name (default {DEFAULT_CELL})")
    inst.add_argument(
        "--prefix", default="/opt/cadence", help="where the venv and Python go (default /opt/cadence)"
    )
    inst.add_argument(
        "--services",
        default="",
        help=f"what runs on this host, comma-separated, of {', '.join((*GRAPH_SERVICES, 'router'))} "
        "(default: the whole cell and its router, its ECG from the operator twin for --strap twin, else from "
        "the gateway)",
    )
    inst.add_argument(
        "--router-host", default="", help="where other hosts reach the router (default: hostname)"
    )
    inst.add_argument(
        "--port", type=positive_int(1), default=7447, help="the router's TLS port (default 7447)"
    )
    inst.add_argument(
        "--join", metavar="CELL.json", help="the first host's /etc/cadence/credentials/cell.json"
    )
    inst.add_argument("--python", metavar="PATH", help="the interpreter for the venv (default: see README)")
    inst.add_argument(
        "--from", dest="source", metavar="SPEC", help="what to install (default: this checkout)"
    )
    inst.add_argument("--no-venv", action="store_true", help="files and units only")
    inst.add_argument("--no-systemctl", action="store_true", help="no daemon-reload or enable")
    inst.add_argument("--dry-run", action="store_true", help="print every file it would write, and stop")
    inst.set_defaults(func=cmd_install)

    uninst = sub.add_parser(
        "uninstall", help="remove what `cadence install` wrote (keeps /var/lib/cadence, the data)"
    )
    uninst.add_argument("--keep-venv", action="store_true", help="leave the venv and Python under the prefix")
    uninst.set_defaults(func=cmd_uninstall)
