"""What a deployed cell is made of, as pure functions: the bus's accounts and the router's
access control, derived from the topology so the two can never disagree; the Zenoh configs of the router
and of each client; the commented deployment config. ``cadence install`` writes what these return.

The rules (DESIGN §11):
- One account per service, plus ``operator`` (``cadence calibrate``, ``cadence robot resume``, an HMI),
  ``separation_sensor`` (``cadence separation``: the scanners' adapters) and ``monitor`` (``zenoh
  subscribe``, ``cadence record``). Each has its own random password and its own certificate whose common
  name is the account's identity: the router requires both (mTLS and user-password), and its ACL names
  each subject by both, so one stolen secret opens nothing.
- An identity is the cell's and the role's, ``<cell>-<role>`` (``identity``): the rules of many cells on one
  router (a line's, a plant's: ``merged``) grant each only its own cell's keys, where bare role names let
  cell1's separation sensor say where people are in cell2.
- Everyone may read their own cell. Each account may publish, and answer queries for, only the keys the
  topology names it the publisher of, and its own ``health/<account>`` (never another's). Only the operator
  may ask ``robot/resume``. An account the cell does not run (the operator twin on a cell with a strap, the
  gateway on a twin's) is not in the router's ACL at all: it may do nothing, not even read.
- The router is the only listener on the network; every service is its client.
"""

from __future__ import annotations

import ast
import base64
import inspect
import io
import json
import tokenize
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import msgspec

from schemas.topology import (
    HEALTH,
    OPERATOR_SEPARATION_OF,
    PLANT_SCOPE,
    ROLES,
    ROOT,
    TOPICS,
    Topic,
    sensor_account,
    source_chunk,
)

# One account per process that joins the bus: a service's or a tool's, one per role of the graph.
ACCOUNTS = tuple(r.name for r in ROLES if r.kind != "sim")
ROUTER_PORT = 7447


def identity(cell: str, account: str) -> str:
    """An account's name on the bus (certificate CN and username). Roles have no '-', so the last one
    splits it back."""
    return f"{cell}-{account}"


def publishers(topic: Topic[Any]) -> set[str]:
    """The accounts that may publish ``topic`` (and answer queries for it)."""
    return set(topic.publishers) & set(ACCOUNTS)


def askers(topic: Topic[Any]) -> set[str]:
    """The accounts that may query ``topic``."""
    return set(topic.askers) & set(ACCOUNTS)


def _acl_key(cell: str, topic: Topic[Any]) -> str:
    # A queryable is declared on the family (the store serves pareto/**), and Zenoh's ACL compares key
    # expressions by inclusion: pareto/* does not include pareto/**.
    suffix = topic.suffix
    if "*" in suffix:
        suffix = suffix.split("*", 1)[0] + "**"
    return f"{ROOT}/{PLANT_SCOPE if topic.scope == 'plant' else cell}/{suffix}"


# the plant's own keys (``Topic.scope``), and what crosses a plant's links for them: a store's question
# and its answers, never a put
PLANT_KEYS = sorted({_acl_key("", t) for t in TOPICS if t.scope == "plant"})
ASKING = ["query", "reply", "declare_queryable"]


def _allow(rule_id: str, flows: list[str], messages: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": flows, "messages": messages, "key_exprs": keys}


READING = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
RECEIVING = ["put", "delete", "reply", "liveliness_token"]


def access_control(
    cell: str, accounts: tuple[str, ...] = ACCOUNTS, sensors: tuple[str, ...] = ()
) -> dict[str, Any]:
    """The router's ``access_control`` section: default deny, every rule derived from the graph, for the
    ``accounts`` this cell runs; and an account for each of its declared separation ``sensors`` (source
    names, `cadence install --scanner`), which may put on that source's own key and nothing else: so a
    reading that comes on a declared source's key comes from that source's account (the executor takes
    it there only under that source's name)."""
    everything = [f"{ROOT}/{cell}/**"]
    read, receive = f"{cell}: read", f"{cell}: receive"
    rules = [
        _allow(read, ["ingress", "egress"], READING, everything),
        _allow(receive, ["egress"], [*RECEIVING, "query", "declare_queryable"], everything),
    ]
    own_keys = {sensor_account(s): f"{ROOT}/{cell}/{OPERATOR_SEPARATION_OF.at(source_chunk(s)).suffix}"
                for s in sensors}  # fmt: skip
    who = {a: identity(cell, a) for a in (*accounts, *own_keys)}
    policies: list[dict[str, Any]] = [{"rules": [read, receive], "subjects": list(who.values())}]
    mine = [t for t in TOPICS if t.scope == "cell"]  # the plant's keys have a rule of their own
    for name, key in own_keys.items():
        rules.append(_allow(f"{cell}: publish {name}", ["ingress"], ["put"], [key]))
        policies.append({"rules": [f"{cell}: publish {name}"], "subjects": [who[name]]})
    for name in accounts:
        health = f"{ROOT}/{cell}/health/{name}"  # its own: health/** would let it speak for the others
        # an owned family's members are their own accounts' (above), never a role's
        keys = sorted({_acl_key(cell, t) for t in mine if name in publishers(t) and t is not HEALTH
                       and not t.owned})  # fmt: skip
        asks = sorted({_acl_key(cell, t) for t in mine if name in askers(t)})
        shared = [t for t in TOPICS if t.scope == "plant" and name in publishers(t) | askers(t)]
        plant = sorted({_acl_key(cell, t) for t in shared})
        own = [f"{cell}: publish {name}", f"{cell}: presence {name}"]
        rules.append(
            _allow(own[0], ["ingress"], ["put", "delete", "declare_queryable", "reply"], [*keys, health])
        )
        rules.append(_allow(own[1], ["ingress"], ["liveliness_token"], [health]))
        if asks:  # a query changes what an answerer does (robot/resume): only those the graph names ask
            own.append(f"{cell}: ask {name}")
            rules.append(_allow(own[-1], ["ingress"], ["query"], asks))
        if plant:  # the plant's keys are no cell's: who asks and answers there, questions and answers only
            own.append(f"{cell}: plant keys {name}")
            rules.append(_allow(own[-1], ["ingress", "egress"], ASKING, plant))
        policies.append({"rules": own, "subjects": [who[name]]})
    # both properties: a subject matches only a session with this certificate AND this username
    subjects = [{"id": i, "cert_common_names": [i], "usernames": [i]} for i in who.values()]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def merged(*acls: dict[str, Any]) -> dict[str, Any]:
    """Several cells' ``access_control`` on one router (a line's or a plant's): their rules, subjects and
    policies side by side. No rule of one names another's keys or subjects, so none widens another."""
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [r for a in acls for r in a["rules"]],
        "subjects": [s for a in acls for s in a["subjects"]],
        "policies": [p for a in acls for p in a["policies"]],
    }


def _b64(pem: bytes) -> str:
    return base64.b64encode(pem).decode()


@dataclass(frozen=True, slots=True)
class Tls:
    """PEM material, inlined into a Zenoh config as base64, so that one file holds all of an account's
    secrets."""

    ca: bytes
    cert: bytes
    key: bytes


def _link(tls: Tls, side: str) -> dict[str, Any]:
    """Mutual TLS on both ends: a router refuses a client without a certificate of this cell's CA."""
    return {
        "tx": {"lease": 1000},
        "tls": {
            "root_ca_certificate_base64": _b64(tls.ca),
            f"{side}_certificate_base64": _b64(tls.cert),
            f"{side}_private_key_base64": _b64(tls.key),
            "enable_mtls": True,
        },
    }


def router_config(
    cell: str,
    listen: Iterable[str],
    tls: Tls,
    users_file: str,
    accounts: tuple[str, ...] = ACCOUNTS,
    plant: bool = False,
    uplink: str | None = None,
    sensors: tuple[str, ...] = (),
) -> dict[str, Any]:
    """A cell's router; ``plant``: a plant's router may connect to it (``PLANT``'s identity in the users
    file): it may read the cell, and nothing else (``with_plant``).

    ``sensors``: the cell's declared separation sources, an account each (``access_control``).

    ``uplink``: the network interface the plant reaches this router on. What leaves on it of the arm's
    state is downsampled here, before it is encrypted and sent, rather than only where the line's router
    takes it in (``plant_router_config``, which still caps it at ``UPLINK_STATE_HZ``, for a cell without
    this): a tenth of the arm's state on the plant's network and in the line's router. It leaves at
    ``UPLINK_SENT_HZ``, under the line's cap, so that the cap lets every one of them in. Zenoh tells links
    apart by interface, not by who is on them: no session of the cell may reach this router over the
    uplink's interface, or it would get the arm's state at that rate too."""
    acl = access_control(cell, accounts, sensors)
    uplink_state = {
        "downsampling": [
            {
                "id": "uplink: state",
                "interfaces": [uplink],
                "flows": ["egress"],
                "messages": ["put"],
                "rules": [{"key_expr": f"{ROOT}/{cell}/robot/state", "freq": UPLINK_SENT_HZ}],
            }
        ]
    }
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": _link(tls, "listen"),
            "auth": {"usrpwd": {"dictionary_file": users_file}},
        },
        "access_control": with_plant(acl, cell) if plant else acl,
        # where a person is goes first, past whatever else is queued on a link (the arm's state, the ECG)
        "qos": {
            "network": [
                {
                    "id": "separation first",
                    "messages": ["put"],
                    "flows": ["ingress", "egress"],
                    "key_exprs": [f"{ROOT}/{cell}/operator/separation/**"],  # each source's key too
                    "overwrite": {"priority": "interactive_high", "express": True},
                }
            ]
        },
        **(uplink_state if uplink else {}),
    }


# --- a plant: a router that connects to many cells' routers ------------------------------------------

PLANT = "plant"  # the plant router's identity on every cell's router (certificate CN and username)
PLANT_MONITOR = identity(PLANT, "monitor")  # who reads the plant (`cadence plant`, `cadence record --plant`)
UPLINK_STATE_HZ = 5.0  # the arm's state per cell as the plant gets it (the cell's own is 50 Hz or more)
# what a cell's uplink sends of it. A cap passes a message that comes at least 1/freq after the last one
# it passed, as its router gets to it; a second cap at the same rate drops each one that the way between
# them brought a little early (a line's router at the plant's priority, on a busy host, takes what waited
# in a bunch), and the plant's view of that cell skips to the next: 0.4 s and more between two. Sent at
# 4.5 Hz (every 240 ms of a 50 Hz state), a message may come up to 40 ms early to the line's 5 Hz cap.
UPLINK_SENT_HZ = 4.5


def with_plant(acl: dict[str, Any], cell: str) -> dict[str, Any]:
    """A cell's rules and the plant's link into it: the plant may declare what it reads (any key: its
    monitor reads every cell at once, ``cadence/*/…``) and receive the cell's keys and what the cell
    listens to; nothing it sends under the cell's keys is let in (no put, no reply, no query: it can say
    nothing about where people are, select no k, resume no robot), whatever the plant router itself
    allows. Under the plant's own keys (``PLANT_KEYS``) questions and answers cross both ways: another
    cell's store asks for a set by its hash, this one's answers (from what it stored), and the reverse;
    a set that comes back is checked by the store that asked, as the executor checks any (never put)."""
    reads, receives, who = f"{cell}: plant reads", f"{cell}: plant receives", f"{cell}: {PLANT}"
    shared = f"{cell}: plant keys"
    return {
        **acl,
        "rules": [
            *acl["rules"],
            _allow(reads, ["ingress"], READING, [f"{ROOT}/**"]),
            _allow(receives, ["egress"], [*RECEIVING, "declare_subscriber"], [f"{ROOT}/{cell}/**"]),
            _allow(shared, ["ingress", "egress"], ASKING, PLANT_KEYS),
        ],
        "subjects": [*acl["subjects"], {"id": who, "cert_common_names": [PLANT], "usernames": [PLANT]}],
        "policies": [*acl["policies"], {"rules": [reads, receives, shared], "subjects": [who]}],
    }


def plant_router_config(
    cells: dict[str, str],
    listen: Iterable[str],
    tls: Tls,
    users_file: str,
    password: str,
    carries: dict[str, list[str]] | None = None,
    upstream: Tls | None = None,
) -> dict[str, Any]:
    """A plant's router, or a line's: it connects to each router of ``cells`` (name to endpoint; a cell's,
    or a line's whose link ``carries`` the keys of the cells behind it) as ``PLANT`` and takes its
    monitors' sessions on ``listen``. The arm's state of each cell it connects to is downsampled to
    ``UPLINK_STATE_HZ`` as it comes in, a rule per cell (one rule over ``cadence/*/robot/state`` would be one
    budget for all of them together); of the cells a line carries, the line's router did that, and a
    second cap would drop what came early (``UPLINK_SENT_HZ``). Its monitors may read every cell and say
    nothing; a link may bring the keys of the cells it carries and nothing of another's.

    ``upstream``: this is a line's router, which a plant's router reads. It connects to its cells with the
    certificate of ``upstream`` (``PLANT``'s, which the cells' routers let in) and shows the plant its own
    (``tls``: ``identity(line, "router")``, which the plant knows the line by); the plant's link may read
    and receive, as a monitor does, and say nothing under any cell's keys."""
    carries = carries or {}
    behind = {name: carries.get(name, [name]) for name in cells}
    readers = [{"id": PLANT_MONITOR, "cert_common_names": [PLANT_MONITOR], "usernames": [PLANT_MONITOR]}]
    if upstream is not None:
        readers.append({"id": PLANT, "cert_common_names": [PLANT], "usernames": [PLANT]})
    rules = [
        _allow("monitor reads", ["ingress"], READING, [f"{ROOT}/**"]),
        _allow("monitor receives", ["egress"], RECEIVING, [f"{ROOT}/**"]),
        _allow("plant keys", ["ingress", "egress"], ASKING, PLANT_KEYS),  # the stores', link to link
    ]
    subjects = list(readers)
    policies = [{"rules": ["monitor reads", "monitor receives"], "subjects": [r["id"] for r in readers]}]
    if upstream is not None:
        policies.append({"rules": ["plant keys"], "subjects": [PLANT]})
    for name, held in behind.items():  # a link, known by its router's certificate (the plant connects to it)
        up, interest = f"{name}: up", f"{name}: interest"
        rules += [
            _allow(up, ["ingress"], [*RECEIVING, "declare_queryable"], [f"{ROOT}/{c}/**" for c in held]),
            _allow(interest, ["egress"], READING, [f"{ROOT}/**"]),
        ]
        subjects.append({"id": name, "cert_common_names": [identity(name, "router")]})
        policies.append({"rules": [up, interest, "plant keys"], "subjects": [name]})
    link = _link(tls, "listen")
    mine = upstream or tls
    link["tls"] |= {"connect_certificate_base64": _b64(mine.cert),
                    "connect_private_key_base64": _b64(mine.key)}  # fmt: skip
    return {
        "mode": "router",
        "connect": {"endpoints": list(cells.values())},
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": link,
            "auth": {"usrpwd": {"dictionary_file": users_file, "user": PLANT, "password": password}},
        },
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        },
        "downsampling": [
            {
                "id": f"{cell}: state",
                "flows": ["ingress"],
                "messages": ["put"],
                "rules": [{"key_expr": f"{ROOT}/{cell}/robot/state", "freq": UPLINK_STATE_HZ}],
            }
            for cell in cells
            if cell not in carries
        ],
    }


def client_config(cell: str, account: str, password: str, connect: Iterable[str], tls: Tls) -> dict[str, Any]:
    return {
        "mode": "client",
        "connect": {"endpoints": list(connect)},
        "listen": {"endpoints": []},  # a client listens nowhere: the router is the only listener
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": _link(tls, "connect"),
            "auth": {"usrpwd": {"user": identity(cell, account), "password": password}},
        },
    }


def users_file(cell: str, passwords: dict[str, str]) -> str:
    return "".join(f"{identity(cell, a)}:{p}\n" for a, p in sorted(passwords.items()))


def to_json5(cfg: dict[str, Any], comment: str) -> str:
    lines = "".join(f"// {line}\n" for line in comment.splitlines())
    return lines + json.dumps(cfg, indent=2) + "\n"


# --- the deployment's config: every key of every section, commented -----------------------------------


def _field_comments(kind: type) -> dict[str, str]:
    """The comments written beside (or just above) each field of a settings struct, from its source."""
    try:
        src = inspect.getsource(kind)
    except (OSError, TypeError):
        return {}
    trailing: dict[int, str] = {}
    alone: dict[int, str] = {}  # comment lines of their own, which describe the field below them
    lines = src.splitlines()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            row = tok.start[0]
            (alone if lines[row - 1].lstrip().startswith("#") else trailing)[row] = text
    out: dict[str, str] = {}
    cls = ast.parse(src).body[0]
    assert isinstance(cls, ast.ClassDef)
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            above: list[str] = []
            row = node.lineno - 1
            while row in alone:
                above.insert(0, alone[row])
                row -= 1
            text = " ".join([*above, trailing.get(node.lineno, "")]).strip()
            if text:
                out[node.target.id] = text
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, msgspec.Struct):
        v = msgspec.to_builtins(v)
    if isinstance(v, dict):  # an inline table
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items() if x is not None) + " }"
    raise TypeError(f"no TOML for {v!r}")


def _range(t: msgspec.inspect.Type) -> str:
    if isinstance(t, msgspec.inspect.UnionType):
        return " or ".join(filter(None, (_range(x) for x in t.types)))
    if isinstance(t, msgspec.inspect.LiteralType):
        return " | ".join(json.dumps(v) for v in t.values)
    lo = getattr(t, "ge", None) if getattr(t, "ge", None) is not None else getattr(t, "gt", None)
    hi = getattr(t, "le", None) if getattr(t, "le", None) is not None else getattr(t, "lt", None)
    if lo is not None or hi is not None:
        return f"{lo if lo is not None else '…'}–{hi if hi is not None else '…'}"
    return ""


def settings_toml(name: str, kind: type, values: dict[str, Any], header: str = "") -> str:
    """``[name]`` with every field of ``kind``: the ones in ``values`` set, the others commented out at
    their defaults, each with its range and the comment from the source."""
    info = msgspec.inspect.type_info(kind)
    assert isinstance(info, msgspec.inspect.StructType)
    notes = _field_comments(kind)
    lines = [f"[{name}]"] if not header else [header, f"[{name}]"]
    nested: list[str] = []
    for f in info.fields:
        if isinstance(f.type, msgspec.inspect.StructType):
            sub = values.get(f.name, {})
            nested.append(settings_toml(f"{name}.{f.name}", f.type.cls, sub if isinstance(sub, dict) else {}))
            continue
        why = "; ".join(filter(None, (_range(f.type), notes.get(f.name))))
        tail = f"  # {why}" if why else ""
        if f.name in values:
            lines.append(f"{f.name} = {_toml_value(values[f.name])}{tail}")
        elif f.default is msgspec.NODEFAULT or f.default is None:
            lines.append(f"# {f.name} =  # unset{'; ' + why if why else ''}")
        else:
            lines.append(f"# {f.name} = {_toml_value(f.default)}{tail}")
    return "\n".join([*lines, "", *nested])
