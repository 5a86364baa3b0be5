"""Planned sets shipped as data (``deploy/sets/<task>.json``), named by the content hash of what they were
planned from: the Pareto store serves one, and the simulated study runs on one, instead of planning, when
a path's content hash matches (issue 53).

Why: planning is a function of its inputs and seed on one machine, not across machines. NSGA-II turns a
last-bit difference in an objective into another tournament winner, and then into another front: numpy
picks its exp, power and cbrt kernels per CPU feature (AVX-512 or not), OpenBLAS its solve and matmul
kernels per core, and SLSQP's BLAS does the same. On one AMD EPYC, the example task's middle solutions moved
by up to 0.2 s between those settings while the ends agreed to 1e-7. A shipped set is an input instead:
the same bytes on every machine, and ``sets_digest`` names them in every summary, study and session file.

`cadence plan TASK --ship FILE` writes such a file; a file that does not decode, or a set in it whose
inputs no longer match, is passed over (the store plans, the study too), never served.
"""

from __future__ import annotations

import functools
import hashlib
import logging
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import msgspec
import numpy as np
from numpy.typing import NDArray

from common.runtime.clock import wall_ns
from common.runtime.errors import InputError
from common.runtime.resources import SHIPPED_SETS
from common.trajectory.planner import ParetoResult, content_hash, plan_path
from common.trajectory.task import PathPlan, Task
from schemas.pareto import Limits, ParetoSet, ParetoSolution

log = logging.getLogger("cadence.sets")


class ShippedSets(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One file: the sets of one task program's paths, and the digest of their solutions."""

    task: str
    sets_sha256: str
    sets: list[ParetoSet]


def as_message(result: ParetoResult, digest: str, t_ns: int | None = None) -> ParetoSet:
    """A planning result as the wire message the store keeps and serves."""
    start, end = result.path.boundary.ends()
    return ParetoSet(
        t_ns=wall_ns() if t_ns is None else t_ns,
        seq=0,
        path_id=result.path.id,
        content_hash=digest,
        constraints=result.settings.constraints,
        waypoints=result.path.waypoints.tolist(),
        limits=Limits(**result.limits.as_dict()),
        start=start,
        end=end,
        front=result.front.tolist(),
        solutions=[
            ParetoSolution(k=s.k, h=s.h.tolist(), t_f=s.t_f, f_time=s.f_time, f_jerk=s.f_jerk)
            for s in result.solutions
        ],
    )


def sets_digest(solutions: Mapping[str, Sequence[Sequence[float] | NDArray[np.float64]]]) -> str:
    """The sha256 of every path's solutions (k = 1 … N), paths in name order, each h as little-endian
    float64: two runs with the same digest moved the robot along the same trajectories, bit for bit."""
    sha = hashlib.sha256()
    for pid in sorted(solutions):
        sha.update(pid.encode() + b"\0")
        for h in solutions[pid]:
            sha.update(np.asarray(h, dtype="<f8").tobytes() + b"\1")
    return sha.hexdigest()


def digest_of(sets: Iterable[ParetoSet]) -> str:
    """``sets_digest`` of wire messages."""
    return sets_digest({s.path_id: [x.h for x in s.solutions] for s in sets})


def digest_of_all(sets: Mapping[str, ParetoSet], paths: Iterable[str]) -> str:
    """``digest_of`` the sets of every one of ``paths``; "" when one is missing: a digest of part of a
    task's sets would name sets no run ran on."""
    return digest_of(sets.values()) if set(sets) == set(paths) else ""


def write_shipped(path: Path, task: Task, sets: Sequence[ParetoSet]) -> str:
    """The file ``path`` for ``task``'s sets (stamped t_ns 0: a shipped set has no planning time on the
    machine that serves it); returns its digest."""
    from common.runtime.storage import write_readable

    stamped = [msgspec.structs.replace(s, t_ns=0) for s in sorted(sets, key=lambda s: s.path_id)]
    digest = digest_of(stamped)
    head = msgspec.json.encode({"task": task.name, "sets_sha256": digest})[:-1]
    body = b",\n".join(msgspec.json.encode(s) for s in stamped)  # a line per set: a diff says which moved
    write_readable(path, head + b',\n"sets": [\n' + body + b"\n]}\n")
    return digest


def read_shipped(path: Path) -> ShippedSets:
    """One file, checked: it decodes, and its digest is that of its sets (an edit by hand is refused)."""
    try:
        doc = msgspec.json.decode(path.read_bytes(), type=ShippedSets)
    except OSError as exc:
        raise InputError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    except (msgspec.ValidationError, msgspec.DecodeError) as exc:
        raise InputError(f"{path}: not a file of shipped sets: {exc}") from None
    if digest_of(doc.sets) != doc.sets_sha256:
        raise InputError(f"{path}: its sets are not those it names ({doc.sets_sha256[:12]}…): edited?")
    return doc


@functools.cache
def _shipped(folder: Path) -> dict[tuple[str, str], ParetoSet]:
    found: dict[tuple[str, str], ParetoSet] = {}
    for f in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            doc = read_shipped(f)
        except InputError as exc:
            log.warning("%s; passed over, its paths are planned", exc)
            continue
        found.update({(s.path_id, s.content_hash): s for s in doc.sets})
    return found


def shipped(path_id: str, content_hash: str, folder: Path = SHIPPED_SETS) -> ParetoSet | None:
    """The shipped set planned from exactly these inputs, if there is one."""
    return _shipped(folder).get((path_id, content_hash))


def shipped_or_planned(path: PathPlan, task: Task) -> ParetoSet:
    """The set a cell would serve for ``path`` on a first start: the shipped one planned from exactly
    these inputs, else one planned here, now."""
    digest = content_hash(path, task.limits, task.planner)
    return shipped(path.id, digest) or as_message(plan_path(path, task.limits, task.planner), digest)
