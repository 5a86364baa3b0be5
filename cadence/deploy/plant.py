"""A plant's router and what each cell needs to let it in (`cadence plant-router`, `cadence install
--plant`): pure functions from the plant's secret and the cells' public CA certificates to files.

Every cell keeps its own CA. The plant has one of its own: a cell's router trusts it beside the cell's
(so the plant router's certificate opens the link), and the plant router trusts every cell's (so each
cell router's certificate does). What a cell is given (``plant.json``) holds no key: the plant's CA
certificate and the password the plant logs in with. The plant's own secret (``plant-secret.json``, mode
0600) holds its CA's key and that password, so that running it again keeps them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cadence.deploy import cell
from cadence.deploy.pki import Pem, issue, load_ca, make_ca, new_password, read_secrets
from common.runtime.errors import InputError


@dataclass(frozen=True, slots=True)
class PlantSecret:
    ca: Pem
    password: str

    def to_json(self) -> str:
        return json.dumps({"ca_cert": self.ca.cert.decode(), "ca_key": self.ca.key.decode(),
                           "password": self.password}, indent=2)  # fmt: skip

    def for_cells(self) -> str:
        """``plant.json``: what every cell's install takes (`--plant`): no key."""
        return json.dumps({"ca_cert": self.ca.cert.decode(), "password": self.password}, indent=2)


@dataclass(frozen=True, slots=True)
class PlantForCell:
    """What a cell's router needs to let the plant's router read it: its CA certificate and its password."""

    ca_cert: bytes
    password: str


def new_secret() -> PlantSecret:
    return PlantSecret(make_ca("plant"), new_password())


def load_secret(path: Path) -> PlantSecret:
    def parse(raw: Any) -> PlantSecret:
        secret = PlantSecret(Pem(raw["ca_cert"].encode(), raw["ca_key"].encode()), str(raw["password"]))
        load_ca(secret.ca)
        return secret

    return read_secrets(path, "a plant secret from `cadence plant-router`", parse)


def load_for_cell(path: Path) -> PlantForCell:
    def parse(raw: Any) -> PlantForCell:
        ca = str(raw["ca_cert"]).encode()
        if b"BEGIN CERTIFICATE" not in ca or "ca_key" in raw:
            raise ValueError("expected the plant's CA certificate and password only (plant.json)")
        return PlantForCell(ca, str(raw["password"]))

    return read_secrets(path, "a plant.json from `cadence plant-router`", parse)


def parse_cell(spec: str) -> tuple[str, str, Path, str | None]:
    """``NAME=ENDPOINT=CA.pem[=LINE]``: a cell, where its router listens, its CA certificate (its
    ``/etc/cadence/credentials/ca.pem``) and the line whose router reads it (none: the plant's does)."""
    parts = spec.split("=")
    if len(parts) not in (3, 4) or not all(parts):
        raise InputError(
            f"--cell {spec!r}: expected NAME=ENDPOINT=CA.pem or NAME=ENDPOINT=CA.pem=LINE "
            "(e.g. c1=tls/10.0.1.5:7447=c1.pem=line1)"
        )
    return parts[0], parts[1], Path(parts[2]), parts[3] if len(parts) == 4 else None


def parse_line(spec: str) -> tuple[str, str]:
    """``NAME=ENDPOINT``: a line, and where its router listens for the plant's."""
    parts = spec.split("=")
    if len(parts) != 2 or not all(parts):
        raise InputError(f"--line {spec!r}: expected NAME=ENDPOINT (e.g. line1=tls/10.0.1.2:7448)")
    return parts[0], parts[1]


def _host(endpoint: str) -> str:
    return endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")


def plant_files(
    secret: PlantSecret,
    cells: dict[str, tuple[str, bytes]],
    listen: str,
    hosts: list[str],
    folder: Path,
    lines: dict[str, tuple[str, list[str]]] | None = None,
) -> dict[str, tuple[str, int]]:
    """The plant router's files in ``folder``, by name, with their modes: its config and its users file,
    its monitor's credentials, ``plant.json`` for the cells and its own secret. ``cells``: name to
    (endpoint, CA certificate). ``lines``: name to (endpoint, its cells): each line's router, in
    ``LINE/``, reads its cells and the plant's router reads the lines; without lines the plant's router
    reads every cell itself."""
    leaf = issue(secret.ca, cell.PLANT, "plant", hosts)
    users = str(folder / "users.txt")
    files: dict[str, tuple[str, int]] = {}
    if lines:
        for line, (endpoint, members) in lines.items():
            trusted = secret.ca.cert + b"".join(cells[c][1] for c in members)
            own = issue(secret.ca, cell.identity(line, "router"), line, [_host(endpoint)])
            line_users = str(folder / line / "users.txt")
            own_tls, uplink = cell.Tls(trusted, own.cert, own.key), cell.Tls(trusted, leaf.cert, leaf.key)
            reads = {c: cells[c][0] for c in members}
            router = cell.plant_router_config(
                reads, [endpoint], own_tls, line_users, secret.password, upstream=uplink
            )
            said = f"Line {line}'s router: it reads {', '.join(members)}; the plant's router reads it."
            files[f"{line}/router.json5"] = (cell.to_json5(router, said), 0o600)
            files[f"{line}/users.txt"] = (f"{cell.PLANT}:{secret.password}\n", 0o600)
        # the lines' certificates are the plant's CA's: it trusts no cell's
        links = {line: endpoint for line, (endpoint, _) in lines.items()}
        carries: dict[str, list[str]] | None = {line: members for line, (_, members) in lines.items()}
        trusted = secret.ca.cert
    else:  # the plant's router reads every cell itself, and trusts each cell's CA
        links = {c: endpoint for c, (endpoint, _) in cells.items()}
        carries = None
        trusted = secret.ca.cert + b"".join(ca for _, ca in cells.values())
    tls = cell.Tls(trusted, leaf.cert, leaf.key)
    router = cell.plant_router_config(links, [listen], tls, users, secret.password, carries=carries)
    said = f"The plant's router: it reads {', '.join(links)}."
    monitor_password = new_password()
    monitor_leaf = issue(secret.ca, cell.PLANT_MONITOR, "plant", [cell.PLANT_MONITOR])
    monitor_tls = cell.Tls(secret.ca.cert, monitor_leaf.cert, monitor_leaf.key)
    monitor = cell.client_config(cell.PLANT, "monitor", monitor_password, [listen], monitor_tls)
    return {
        **files,
        "router.json5": (cell.to_json5(router, said), 0o600),
        "users.txt": (f"{cell.PLANT_MONITOR}:{monitor_password}\n", 0o600),
        "plant-monitor.json5": (
            cell.to_json5(monitor, "The plant monitor's account: it reads every cell and says nothing."),
            0o600,
        ),
        "plant.json": (secret.for_cells(), 0o644),
        "plant-secret.json": (secret.to_json(), 0o600),
    }
