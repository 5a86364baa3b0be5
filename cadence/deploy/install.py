"""``cadence install`` and ``cadence uninstall``: a robot cell in one command.

What it writes (every file is in the manifest, ``/etc/cadence/installed.json``, so uninstall removes
exactly that and keeps the data folder):
- the system user ``cadence`` (``/etc/sysusers.d/cadence.conf``);
- ``/etc/cadence/cadence.toml``: every key of every section, commented, set for the real hardware (or the
  twin and the sim arm); kept if it exists, so a re-install never loses an edit;
- ``/etc/cadence/credentials/``: the cell's CA, one Zenoh account per service (random password, its own
  certificate), the router's config with the ACL generated from the topology, and ``cell.json``, the
  bundle a second host joins with (``--join``);
- the units, with the prefix put in, enabled under ``cadence.target``;
- a Python the ``cadence`` user can run, and the venv on it, under the prefix.

Pure parts (what the files say) are in ``cadence/deploy/cell.py`` and ``pki.py``; this module decides what
goes where and does it.
"""

from __future__ import annotations

import contextlib
import grp
import json
import os
import pwd
import re
import shutil
import socket
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from cadence.deploy import cell
from cadence.deploy.pki import Pem, issue, load_ca, make_ca, new_password, read_secrets
from cadence.deploy.plant import PlantForCell, load_for_cell
from common.runtime.errors import InputError
from common.runtime.resources import DEPLOY, EXAMPLE_TASK
from schemas.topology import DEFAULT_CELL, ROLES, SERVICES, sensor_account
from services import registry
from services.executor.settings import SourceSettings
from services.registry import BY_NAME, Service, unit

USER = "cadence"
ETC = Path("/etc/cadence")
CREDS = ETC / "credentials"
DATA = Path("/var/lib/cadence")
TASKS = ETC / "tasks"  # the cell's task programs: the example to start from
UNITS = Path("/etc/systemd/system")
MANIFEST = ETC / "installed.json"
SYSUSERS = Path("/etc/sysusers.d/cadence.conf")
PYTHON_MIN = (3, 11)
HOSTS_ALL = (*SERVICES, "router")
TOOLS = tuple(r.name for r in ROLES if r.kind == "tool")  # operator, separation_sensor, monitor


def cell_services(strap: str) -> tuple[str, ...]:
    """What a whole cell runs on one host: its services (one ECG source: the operator twin for ``--strap
    twin``, else the gateway: the strap, or a replay) and the router."""
    runs = {s.name for s in registry.cell(twin=strap == "twin")}
    return (*(s for s in SERVICES if s in runs), "router")


def cell_accounts(strap: str) -> tuple[str, ...]:
    """The bus accounts the cell's router lets in: its services and the tools. The twin, which says where
    its simulated person is, has no account on a cell with a real strap (and a real scanner)."""
    return tuple(a for a in cell.ACCOUNTS if a in cell_services(strap) or a in TOOLS)


class InstallError(InputError):
    """The install cannot go on; the message says what to do."""


@dataclass(frozen=True, slots=True)
class Options:
    robot: str = "sim"  # "sim" or the UR controller's address
    strap: str = "Polar H10"  # "twin", "replay", or the H10's MAC address or advertised name
    cell_name: str = DEFAULT_CELL
    prefix: Path = Path("/opt/cadence")
    services: tuple[str, ...] = ()  # what runs on this host; "router" for the cell's router; () the cell's
    router_host: str = ""  # where other hosts reach the router (default: this host's name)
    port: int = cell.ROUTER_PORT
    join: Path | None = None  # the first host's credentials/cell.json
    python: str | None = None
    source: str | None = None  # what to install in the venv (default: this checkout, or cadence==VERSION)
    venv: bool = True  # False: write files and units only (a venv already there)
    # the cell's separation sources (`--scanner`): given, the executor's monitoring is on and requires them
    scanners: tuple[SourceSettings, ...] = ()
    systemctl: bool = True  # False: no daemon-reload / enable (an image being built)
    # staged into this folder, as DESTDIR does (`--root`): every file at root/<its path>, naming the real
    # paths inside; no user, no ownership, no venv, no systemctl (a packager's or an inspector's copy)
    root: Path | None = None
    # a plant's router may read this cell (`--plant plant.json`, from `cadence plant-router`): the router
    # trusts the plant's CA beside the cell's and takes its password; it lets nothing in from it
    plant: Path | None = None
    # the network interface the plant reaches the router on (`--uplink-interface`): the arm's state
    # leaves on it at the plant's rate (``router_config``'s ``uplink``)
    uplink: str | None = None


@dataclass
class File:
    path: Path
    text: str
    mode: int = 0o640
    group: str | None = USER  # owner is root; the group may read
    secret: bool = False
    keep: bool = False  # an existing file is kept (the admin's config)


@dataclass
class Plan:
    files: list[File] = field(default_factory=list)
    dirs: list[tuple[Path, int, str | None, str | None]] = field(
        default_factory=list
    )  # path, mode, user, grp
    notes: list[str] = field(default_factory=list)


# --- what to write ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Bundle:
    """What every host of one cell shares: the CA (to issue each host's certificates), every account's
    password and where the router is. ``credentials/cell.json``, mode 0600: the cell's root secret."""

    cell: str
    router_host: str
    port: int
    ca: Pem
    passwords: dict[str, str]

    def to_json(self) -> str:
        return json.dumps(
            {
                "cell": self.cell,
                "router_host": self.router_host,
                "port": self.port,
                "ca_cert": self.ca.cert.decode(),
                "ca_key": self.ca.key.decode(),
                "passwords": self.passwords,
            },
            indent=2,
        )

    @classmethod
    def load(cls, path: Path) -> Bundle:
        def parse(raw: Any) -> Bundle:
            bundle = cls(
                cell=str(raw["cell"]),
                router_host=str(raw["router_host"]),
                port=int(raw["port"]),
                ca=Pem(raw["ca_cert"].encode(), raw["ca_key"].encode()),
                # an account added since the bundle was made gets its password now (the bundle is rewritten)
                passwords={
                    **{a: str(p) for a, p in raw["passwords"].items()},  # the declared sources' too
                    **{a: str(raw["passwords"].get(a) or new_password()) for a in cell.ACCOUNTS},
                },
            )
            load_ca(bundle.ca)
            return bundle

        return read_secrets(path, "a cell bundle from `cadence install`", parse, InstallError)


def sensor_accounts(opts: Options) -> dict[str, str]:
    """The bus account of each declared separation source (``--scanner``), by source name; two that would
    share an account (``scanner:front`` and ``scanner_front``) are refused."""
    accounts = {s.name: sensor_account(s.name) for s in opts.scanners}
    if len(set(accounts.values())) < len(accounts):
        raise InstallError(f"--scanner: {', '.join(accounts)} would share a bus account (its key chunk: "
                           "what is not a letter, a digit or '_' reads as '_'): name them apart")  # fmt: skip
    return accounts


def with_sensors(bundle: Bundle, opts: Options) -> Bundle:
    """The bundle with a password for each declared source's account it has none for yet."""
    new = {a: new_password() for a in sensor_accounts(opts).values() if a not in bundle.passwords}
    return replace(bundle, passwords={**bundle.passwords, **new}) if new else bundle


def new_bundle(opts: Options) -> Bundle:
    return with_sensors(
        Bundle(
            cell=opts.cell_name,
            router_host=opts.router_host or socket.gethostname(),
            port=opts.port,
            ca=make_ca(opts.cell_name),
            passwords={a: new_password() for a in cell.ACCOUNTS},
        ),
        opts,
    )


def config_toml(opts: Options, bundle: Bundle) -> str:
    """``/etc/cadence/cadence.toml``: the hardware's values set, every other key commented at its default."""
    from common.runtime.bus import BusConfig
    from common.runtime.config import CommonSettings

    twin = opts.strap == "twin"
    head = (
        f"# Cadence, cell {bundle.cell}: written by `cadence install`"
        f" (robot: {opts.robot}; strap: {opts.strap}).\n"
        "# Every key of every section is here: set ones are the install's, commented ones show their\n"
        "# defaults, ranges and meaning. Any key can also be set as CADENCE_<SECTION>_<KEY> in\n"
        "# /etc/cadence/cadence.env. After an edit: systemctl restart cadence.target\n"
    )
    sections = [
        cell.settings_toml("cadence", CommonSettings, {"cell": bundle.cell, "data_dir": str(DATA)}),
        cell.settings_toml(
            "bus",
            BusConfig,
            {"mode": "client"},
            "# each unit sets config_file to its own account (credentials/<service>.json5)",
        ),
        *(cell.settings_toml(s.name, s.settings(), *installed(s, opts)) for s in registry.cell(twin)),
    ]
    return head + "\n" + "\n".join(sections)


CALIBRATE = "# run `cadence calibrate` once per operator: it writes the calibration this reads"
NO_SCANNER = (
    "# separation monitoring is off: no --scanner was given. To turn it on, declare each source\n"
    '# (separation_sources = [{ name = "scanner:front", pose = [x, y, z, yaw], detects = "legs" }])\n'
    "# and set separation = true; it slows the arm, the scanner's own stop is the safety function"
)


def installed(service: Service, opts: Options) -> tuple[dict[str, object], str]:
    """A service's settings that the install sets, from what it needs of the cell (services/registry.py),
    and the note above its section."""
    values: dict[str, object] = {}
    notes = []
    for need in service.needs:
        if need == "task":
            values["task"] = str(TASKS / EXAMPLE_TASK.name)
        elif need == "robot" and opts.robot == "sim":
            values["backend"] = "sim"
        elif need == "robot":
            values |= {"backend": "ur_rtde", "host": opts.robot}
        elif need == "strap" and opts.strap == "replay":
            values["source"] = "replay"
        elif need == "strap":
            values |= {"source": "polar", "strap": opts.strap}
        elif need == "resting_rr" and opts.strap == "twin":
            from common.sim.twin import TwinParams

            values["rr_rest_s"] = TwinParams().rr_rest_s  # the twin's resting RR: no `cadence calibrate`
        elif need == "resting_rr":
            notes.append(CALIBRATE)
        elif need == "separation" and opts.scanners:  # monitoring on, each source required (DESIGN §8)
            values |= {"separation": True, "separation_sources": list(opts.scanners),
                       "separation_undeclared": "refuse"}  # fmt: skip
        elif need == "separation":
            notes.append(NO_SCANNER)
    return values, "\n".join(notes)


def _connect(opts: Options, bundle: Bundle) -> list[str]:
    host = "127.0.0.1" if "router" in opts.services else bundle.router_host
    return [f"tls/{host}:{bundle.port}"]


def plan(opts: Options, bundle: Bundle, plant: PlantForCell | None = None) -> Plan:
    bundle = with_sensors(bundle, opts)  # a source declared since: its account's password, kept in the bundle
    sensors = sensor_accounts(opts)  # source: account
    p = Plan()
    p.dirs += [
        (ETC, 0o750, "root", USER),
        (CREDS, 0o750, "root", USER),
        (TASKS, 0o750, "root", USER),
        (DATA, 0o750, USER, USER),
    ]
    p.files.append(File(SYSUSERS, (DEPLOY / "systemd" / "cadence.sysusers").read_text(), 0o644, None))
    p.files.append(File(ETC / "cadence.toml", config_toml(opts, bundle), keep=True))
    p.files.append(File(TASKS / EXAMPLE_TASK.name, EXAMPLE_TASK.read_text(), keep=True))
    p.files.append(File(ETC / "cadence.env", (DEPLOY / "systemd" / "cadence.env").read_text(), keep=True))
    p.files.append(File(CREDS / "cell.json", bundle.to_json(), 0o600, None, secret=True))
    ca_file = File(CREDS / "ca.pem", bundle.ca.cert.decode(), 0o644, None)
    p.files.append(ca_file)
    hosts = sorted({bundle.router_host, "localhost", "127.0.0.1"})
    if "router" in opts.services:
        leaf = issue(bundle.ca, cell.identity(bundle.cell, "router"), bundle.cell, hosts)
        users = CREDS / "users.txt"
        passwords = cell.users_file(bundle.cell, bundle.passwords)
        trusted = bundle.ca.cert
        if plant is not None:
            passwords += f"{cell.PLANT}:{plant.password}\n"
            trusted += plant.ca_cert
        p.files.append(File(users, passwords, secret=True))
        router = cell.router_config(
            bundle.cell,
            [f"tls/0.0.0.0:{bundle.port}"],
            cell.Tls(trusted, leaf.cert, leaf.key),
            str(users),
            cell_accounts(opts.strap),
            plant=plant is not None,
            uplink=opts.uplink,
            sensors=tuple(sensors),
        )
        p.files.append(
            File(
                CREDS / "router.json5",
                cell.to_json5(
                    router, f"The router of cell {bundle.cell}: mTLS, passwords, ACL from the topology."
                ),
                secret=True,
            )
        )
    # this host's accounts: its services, and the tools' and the declared sources' (root reads those)
    accounts = [s for s in opts.services if s in SERVICES]
    for account in [*accounts, *TOOLS, *sensors.values()]:
        leaf = issue(bundle.ca, cell.identity(bundle.cell, account), bundle.cell, [account])
        cfg = cell.client_config(
            bundle.cell,
            account,
            bundle.passwords[account],
            _connect(opts, bundle),
            cell.Tls(bundle.ca.cert, leaf.cert, leaf.key),
        )
        tool = account in TOOLS or account in sensors.values()
        p.files.append(
            File(
                CREDS / f"{account}.json5",
                cell.to_json5(cfg, f"Bus account '{account}' of cell {bundle.cell}."),
                0o600 if tool else 0o640,
                None if tool else USER,
                secret=True,
            )
        )
    template = (DEPLOY / "systemd" / "cadence-service.in").read_text()
    for s in opts.services:
        name = f"cadence-{s}.service"
        if s in BY_NAME:
            text = unit(BY_NAME[s], template, str(opts.prefix))
        else:  # the router: a unit of its own
            text = (DEPLOY / "systemd" / name).read_text().replace("/opt/cadence", str(opts.prefix))
        p.files.append(File(UNITS / name, text, 0o644, None))
    target = (DEPLOY / "systemd" / "cadence.target").read_text().replace("/opt/cadence", str(opts.prefix))
    p.files.append(File(UNITS / "cadence.target", target, 0o644, None))
    if not opts.systemctl:
        p.notes.append("systemctl: skipped (--no-systemctl)")
    return p


# --- doing it -----------------------------------------------------------------------------------------


def _run(cmd: list[str], what: str, timeout: float = 900.0) -> subprocess.CompletedProcess[str]:
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise InstallError(f"{what}: {' '.join(cmd)}: {exc}") from exc
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-3:]
        raise InstallError(f"{what}: {' '.join(cmd)} exited {r.returncode}: {' / '.join(tail)}")
    return r


def _write(f: File, written: list[str], own: bool = True) -> str:
    if f.keep and f.path.exists():
        return f"kept {f.path} (exists)"
    f.path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=f.path.parent, prefix=f".{f.path.name}.")
    try:
        with os.fdopen(fd, "w") as out:
            out.write(f.text)
        os.chmod(tmp, f.mode)
        if own:
            os.chown(tmp, 0, grp.getgrnam(f.group).gr_gid if f.group else 0)
        os.replace(tmp, f.path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    written.append(str(f.path))
    return f"wrote {f.path} ({f.mode:o})"


def _ensure_user() -> None:
    with contextlib.suppress(KeyError):
        pwd.getpwnam(USER)
        return
    if shutil.which("systemd-sysusers"):
        _run(["systemd-sysusers", str(SYSUSERS)], "creating the user")
    else:
        _run(["useradd", "--system", "--home-dir", str(DATA), "--no-create-home", USER], "creating the user")


def _hidden(path: str) -> bool:
    """Under a folder the units hide (ProtectHome=yes) or that root keeps to itself."""
    return any(Path(path).is_relative_to(p) for p in ("/root", "/home", "/run/user"))


def _runs_as_user(python: str) -> str | None:
    """Why the service user cannot use this interpreter, or None."""
    real = os.path.realpath(python)
    if _hidden(real):
        return f"{real} is under a home folder (ProtectHome=yes hides it, and /root is mode 700)"
    probe = f"import sys; sys.exit(0 if sys.version_info >= {PYTHON_MIN} else 3)"
    runner = ["runuser", "-u", USER, "--"] if shutil.which("runuser") else ["su", "-s", "/bin/sh", USER, "-c"]
    cmd = [*runner, real, "-c", probe] if runner[0] == "runuser" else [*runner, f"{real} -c '{probe}'"]
    r = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if r.returncode == 3:
        return f"{real} is older than Python {'.'.join(map(str, PYTHON_MIN))}"
    if r.returncode != 0:
        return f"{real} does not run as {USER}: {(r.stderr or r.stdout).strip()[-200:]}"
    return None


def ensure_python(opts: Options, uv: str, say: list[str]) -> str:
    """An interpreter the ``cadence`` user can run: the one asked for, else one uv installs under the
    prefix, else a system one that passes the same check. Never a link into root's home."""
    if opts.python:
        why = _runs_as_user(opts.python)
        if why:
            raise InstallError(f"--python {opts.python}: {why}")
        return os.path.realpath(opts.python)
    where = opts.prefix / "python"
    r = subprocess.run(
        [uv, "python", "install", "--install-dir", str(where), "3.12"],
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
    )
    if r.returncode == 0:
        found = sorted(where.glob("cpython-*/bin/python3"))
        if found and _runs_as_user(str(found[-1])) is None:
            say.append(f"python: {found[-1]} (uv, under the prefix)")
            return str(found[-1])
    say.append(f"python: uv could not install one under {where} ({(r.stderr or '').strip()[-120:]})")
    base = getattr(sys, "_base_executable", None)  # the interpreter a venv was made from
    for cand in (base, "/usr/bin/python3.13", "/usr/bin/python3.12", "/usr/bin/python3.11"):
        if cand and Path(cand).exists() and _runs_as_user(cand) is None:
            say.append(f"python: {os.path.realpath(cand)} (the service user can run it)")
            return os.path.realpath(cand)
    raise InstallError(
        f"no Python >= {'.'.join(map(str, PYTHON_MIN))} that the {USER} user can run: "
        "install one (apt install python3.11, or uv python install with network) and pass --python PATH"
    )


def _checkout() -> Path | None:
    root = Path(__file__).resolve().parents[2]  # cadence/deploy/install.py in a checkout
    return root if (root / "uv.lock").exists() and (root / "pyproject.toml").exists() else None


def build_venv(opts: Options, say: list[str]) -> None:
    uv = shutil.which("uv")
    if uv is None:
        raise InstallError("uv is not on PATH: pip install uv (it builds the services' venv)")
    python = ensure_python(opts, uv, say)
    venv = opts.prefix / ".venv"
    _run([uv, "venv", "--allow-existing", "--python", python, str(venv)], "creating the venv")
    py = str(venv / "bin" / "python")
    # compiled now: the service accounts cannot write bytecode into the install, and every service start
    # would compile numpy and scipy again
    pip = [uv, "pip", "install", "--compile-bytecode", "--python", py]
    src = opts.source or (str(_checkout()) if _checkout() else None)
    if src and Path(src).is_dir() and (Path(src) / "uv.lock").exists():
        with tempfile.NamedTemporaryFile("w", suffix=".txt") as req:
            _run(
                [
                    uv,
                    "export",
                    "--frozen",
                    "--no-dev",
                    "--no-emit-project",
                    "--no-hashes",
                    "--project",
                    src,
                    "-o",
                    req.name,
                ],
                "reading the lock",
            )
            _run([*pip, "-r", req.name], "installing the locked dependencies")
        _run(
            [*pip, "--no-deps", "--reinstall-package", "cadence", src],
            "installing cadence",
        )
    else:
        from importlib.metadata import version

        _run(
            [*pip, src or f"cadence=={version('cadence')}"],
            "installing cadence",
        )
    say.append(f"venv: {venv} on {python}")


def no_systemd(root: Path = Path("/")) -> str:
    """Why ``systemctl`` cannot enable the units here, or "" when it can: systemd must be PID 1
    (``/run/systemd/system`` exists then, as ``sd_booted(3)`` tests)."""
    if not (root / "run/systemd/system").is_dir():
        try:
            init = (root / "proc/1/comm").read_text().strip()
        except OSError:
            init = "unknown"
        return f"this host does not run systemd (PID 1 is {init})"
    if shutil.which("systemctl") is None:
        return "systemctl is not on the PATH"
    return ""


def install(opts: Options, dry_run: bool = False) -> list[str]:
    """Does (or, dry, describes) the install; returns the lines to print."""
    if not set(opts.services) <= set(HOSTS_ALL):
        raise InstallError(
            f"--services: unknown {sorted(set(opts.services) - set(HOSTS_ALL))}; "
            f"expected some of {', '.join(HOSTS_ALL)}"
        )
    opts = replace(opts, services=opts.services or cell_services(opts.strap))
    if wrong := set(opts.services) - set(cell_services(opts.strap)):  # two ECG sources would interleave
        raise InstallError(
            f"--services {', '.join(sorted(wrong))}: with --strap {opts.strap} the ECG comes from "
            f"{'the operator twin' if opts.strap == 'twin' else 'the ecg_gateway'}"
        )
    if not re.fullmatch(r"[A-Za-z0-9_\-]{1,64}", opts.cell_name):  # a key chunk, as [cadence] cell
        raise InstallError(f"--cell {opts.cell_name!r}: letters, digits, '_' and '-' only, at most 64")
    if not re.fullmatch(r"[A-Za-z0-9.:\-\[\]]{1,253}", opts.robot):
        raise InstallError(f"--robot {opts.robot!r}: a host name or address, or sim")
    if _hidden(str(opts.prefix.resolve())):  # the units run with ProtectHome=yes: they would never start
        raise InstallError(f"--prefix {opts.prefix}: under a home folder, which the units cannot see "
                           "(ProtectHome=yes; /root is mode 700): give one like /opt/cadence")  # fmt: skip
    if opts.root is not None and opts.root.resolve() == Path("/"):
        raise InstallError("--root /: that is the install itself (run it without --root, as root)")
    existing = CREDS / "cell.json" if opts.root is None else under(opts.root, CREDS / "cell.json")
    if opts.join:
        bundle = Bundle.load(opts.join)
    elif existing.exists():
        bundle = Bundle.load(existing)  # a re-install keeps the cell's CA and passwords
    else:
        bundle = new_bundle(opts)
    p = plan(opts, bundle, load_for_cell(opts.plant) if opts.plant else None)
    say: list[str] = []
    if dry_run:
        for d, mode, user, group in p.dirs:
            say.append(f"mkdir {d} ({mode:o} {user}:{group})")
        for f in p.files:
            say.append(
                f"--- {f.path} ({f.mode:o} root:{f.group or 'root'}){' kept if present' if f.keep else ''}"
            )
            say.append("    <secret: passwords and keys>" if f.secret else f.text.rstrip())
        say.append(f"venv: {opts.prefix}/.venv" if opts.venv else "venv: skipped")
        say += p.notes
        return say
    if opts.root is not None:
        return stage(opts, p, opts.root)
    if os.geteuid() != 0:
        raise InstallError("cadence install writes /etc, /opt and systemd units: run it as root (sudo)")
    if opts.systemctl and (why := no_systemd()):  # before anything is written, not after 626 MB of venv
        raise InstallError(
            f"{why}: nothing was written. Install on a host that runs systemd, or with --no-systemctl to "
            "write the files and the venv only (an image being built), and enable cadence.target later"
        )
    written: list[str] = []
    made: list[str] = []
    SYSUSERS.parent.mkdir(parents=True, exist_ok=True)
    say.append(_write(p.files[0], written))
    _ensure_user()
    uid = pwd.getpwnam(USER).pw_uid
    gid = grp.getgrnam(USER).gr_gid
    for d, mode, user, group in p.dirs:
        if not d.exists():
            made.append(str(d))
        d.mkdir(parents=True, exist_ok=True)
        os.chmod(d, mode)
        os.chown(d, uid if user == USER else 0, gid if group == USER else 0)
    for f in p.files[1:]:
        say.append(_write(f, written))
    if opts.venv:
        if not opts.prefix.exists():
            made.append(str(opts.prefix))
        build_venv(opts, say)
    old = json.loads(MANIFEST.read_text()) if MANIFEST.exists() else {}
    manifest = {
        "files": sorted(set(old.get("files", [])) | set(written)),
        "dirs": sorted(set(old.get("dirs", [])) | set(made)),
        "units": sorted({*old.get("units", []), *(f"cadence-{s}.service" for s in opts.services)}),
        "prefix": str(opts.prefix),
    }
    MANIFEST.write_text(json.dumps(manifest, indent=2))
    if opts.systemctl:
        _run(["systemctl", "daemon-reload"], "reloading systemd")
        _run(["systemctl", "enable", "cadence.target", *manifest["units"]], "enabling the units")
        say.append(
            f"enabled cadence.target: {', '.join(manifest['units'])}; start: systemctl start cadence.target"
        )
    if "router" in opts.services:
        say.append(
            f"a second host joins with: cadence install --join {existing} --services … "
            "(copy that file over a secure channel, then delete the copy)"
        )
    return say


def under(root: Path, path: Path) -> Path:
    return root / path.relative_to("/")


def stage(opts: Options, p: Plan, root: Path) -> list[str]:
    """The install's files under ``root``, each naming the real paths (as DESTDIR staging does), with
    what the host must still do beside them in the manifest: each path's mode and owner, the units to
    enable. A venv is not relocatable (its scripts name their interpreter by path): it is built on the
    host (`cadence install --no-systemctl` there, or the package's own step)."""
    say: list[str] = []
    written: list[str] = []
    for d, mode, _, _ in p.dirs:
        under(root, d).mkdir(parents=True, exist_ok=True)
        os.chmod(under(root, d), mode)
    for f in p.files:
        say.append(_write(replace(f, path=under(root, f.path)), written, own=False))
    owners = {str(d): f"{mode:04o} {user or 'root'}:{group or 'root'}" for d, mode, user, group in p.dirs}
    owners |= {str(f.path): f"{f.mode:04o} root:{f.group or 'root'}" for f in p.files}
    manifest = {
        "files": sorted(str(f.path) for f in p.files),
        "dirs": sorted(str(d) for d, *_ in p.dirs),
        "units": sorted(f"cadence-{s}.service" for s in opts.services),
        "prefix": str(opts.prefix),
        "owners": owners,
        "staged": str(root),
    }
    under(root, MANIFEST).write_text(json.dumps(manifest, indent=2))
    say.append(f"wrote {under(root, MANIFEST)} (every path's mode and owner, the units to enable)")
    say.append(
        f"staged into {root}: no user created, nothing owned by {USER}, no venv (build it on the host under "
        f"{opts.prefix}/.venv), nothing enabled; {under(root, CREDS)} holds this cell's keys and passwords"
    )
    return say


def uninstall(keep_venv: bool = False) -> list[str]:
    if os.geteuid() != 0:
        raise InstallError("cadence uninstall removes what the install wrote: run it as root (sudo)")
    if not MANIFEST.exists():
        raise InstallError(f"{MANIFEST}: not found: nothing was installed here by `cadence install`")
    m = json.loads(MANIFEST.read_text())
    say: list[str] = []
    if shutil.which("systemctl"):
        subprocess.run(
            ["systemctl", "disable", "--now", "cadence.target", *m["units"]], capture_output=True, check=False
        )
    failed: list[str] = []
    for f in m["files"]:
        try:
            os.unlink(f)
            say.append(f"removed {f}")
        except FileNotFoundError:
            pass
        except OSError as exc:  # go on: remove what can be, then say what could not
            failed.append(f"{f}: {exc.strerror or exc}")
    prefix = Path(m["prefix"])
    if not keep_venv:
        for sub in (".venv", "python"):
            if (prefix / sub).exists():
                shutil.rmtree(prefix / sub)
                say.append(f"removed {prefix / sub}")
    for d in sorted(m["dirs"], key=len, reverse=True):
        if Path(d) == DATA:
            continue
        with contextlib.suppress(OSError):
            shutil.rmtree(d) if Path(d).is_relative_to(ETC) else os.rmdir(d)
            say.append(f"removed {d}")
    with contextlib.suppress(FileNotFoundError):
        MANIFEST.unlink()
    if ETC.exists() and not any(ETC.iterdir()):
        ETC.rmdir()
    if shutil.which("systemctl"):
        subprocess.run(["systemctl", "daemon-reload"], capture_output=True, check=False)
    say.append(f"kept {DATA} (the data: Pareto sets, decision state, recordings)")
    if failed:
        raise InstallError("could not remove: " + "; ".join(failed) + " (the rest is removed)")
    return say
