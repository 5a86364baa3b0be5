"""Task programs (TOML): the robot's limits, the paths with their waypoints, and the cycle of moves and
actions between them (DESIGN §8). Loading is strict: a task program that loads can be planned.

A file is decoded in two steps. msgspec checks the shape (types, missing and unknown keys) and gives the
field's path; then the semantic checks run (units, joint ranges, limits that may only be lowered, NaN,
duplicate ids). Every failure is one ``TaskError`` naming the file, the path and the field.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Literal

import msgspec
import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import N_JOINTS, UR16E, JointLimits
from common.runtime.errors import TaskError
from common.trajectory.bspline import Boundary
from schemas.decision import MAX_N
from schemas.pareto import MAX_PATH_S

Unit = Literal["deg", "rad"]
Constraints = Literal["hull", "exact"]

# Relative slack when comparing a task's limit with the table: a limit written in degrees and converted
# to radians must not fail for the last bit of the conversion.
_LIMIT_RTOL = 1e-9
CONTINUITY_TOL_RAD = 1e-6
MAX_WAIT_S = 3600.0
MAX_EARLY_S = 60.0  # a signal older than this at the wait is about another part
MAX_INPUT = 7  # the UR controller's standard digital inputs: DI 0–7
MIN_LIMIT_SHARE = 1e-3  # a limit lowered further than this is a typo, and would plan hour-long paths


# ---- the file's shape (msgspec decodes into these; unknown keys are errors) -------------------------


class _BoundarySpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    velocity: list[float] | None = None
    acceleration: list[float] | None = None
    jerk: list[float] | None = None


class _PathSpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    id: str
    unit: Unit
    waypoints: list[list[float]]
    start: _BoundarySpec = _BoundarySpec()
    end: _BoundarySpec = _BoundarySpec()
    description: str = ""


class _LimitsSpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    unit: Unit
    velocity: list[float] | None = None
    acceleration: list[float] | None = None
    jerk: list[float] | None = None


class PlannerSettings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """NSGA-II and downsampling settings (DESIGN §5), the task's [planner] table as it is decoded.
    ``generations=None`` means the tuned default; change one with ``msgspec.structs.replace``."""

    constraints: Constraints = "exact"
    n_solutions: int = 15
    population: int = 90
    generations: int | None = None
    seed: int = 1
    kappa: float = 10.0


class _StepSpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    move: str | None = None
    gripper: Literal["on", "off"] | None = None
    wait: float | None = None
    wait_for: str | None = None
    # with wait_for only: the seconds the operator has once the robot waits, and what the robot does then
    deadline: float | None = None
    on_late: Literal["wait", "go_on"] = "wait"
    # with wait_for only: the UR's standard digital input (0–7) whose rising edge is this signal
    input: int | None = None
    # with wait_for only: a signal at most this many seconds before the wait opens still counts for it
    early: float | None = None


class _TaskMeta(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    name: str
    description: str = ""


class _TaskSpec(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    task: _TaskMeta
    paths: list[_PathSpec]
    limits: _LimitsSpec | None = None
    planner: PlannerSettings = PlannerSettings()
    cycle: list[_StepSpec] | None = None


# ---- what the rest of Cadence uses ------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class PathPlan:
    """One path: W waypoints in rad (W, 6) and its boundary conditions."""

    id: str
    waypoints: NDArray[np.float64]
    boundary: Boundary
    description: str = ""


@dataclass(frozen=True, slots=True)
class Step:
    """One step of a cycle: exactly one of the fields is set."""

    move: str | None = None
    gripper: Literal["on", "off"] | None = None
    wait: float | None = None
    wait_for: str | None = None
    # a wait_for's deadline: past it, the part is late (an operator error, kind "late"); the robot then
    # keeps waiting ("wait") or goes on without it ("go_on")
    deadline: float | None = None
    on_late: Literal["wait", "go_on"] = "wait"
    input: int | None = None  # a wait_for met by this UR standard digital input's rising edge
    # a signal at most this many seconds before the wait opens counts for it (a part put down as the robot
    # comes); without it only a signal while the robot waits counts (DESIGN §8: a signal is about now)
    early: float | None = None


@dataclass(frozen=True, slots=True)
class Task:
    name: str
    source: str
    limits: JointLimits
    paths: dict[str, PathPlan]
    cycle: list[Step]
    planner: PlannerSettings = field(default_factory=PlannerSettings)
    description: str = ""


def _scale(unit: Unit) -> float:
    return math.pi / 180.0 if unit == "deg" else 1.0


def _translate(file: str, raw: object, err: msgspec.ValidationError) -> TaskError:
    """msgspec says ``Expected `float`, got `str` - at `$.paths[1].waypoints[0][2]```: name the path."""
    text = str(err)
    m = re.search(r" - at `\$\.?(.*)`$", text)
    what = text[: m.start()] if m else text
    loc = m.group(1) if m else "(top level)"
    path_id = None
    pm = re.match(r"paths\[(\d+)\]\.?(.*)", loc)
    if pm and isinstance(raw, dict):
        paths = raw.get("paths")
        i = int(pm.group(1))
        if isinstance(paths, list) and i < len(paths) and isinstance(paths[i], dict):
            pid = paths[i].get("id")
            path_id = pid if isinstance(pid, str) else f"#{i}"
        loc = pm.group(2) or "(the path)"
    return TaskError(file, loc or "(top level)", what, path_id)


def _vector(file: str, values: list[float], fld: str, path_id: str | None = None) -> NDArray[np.float64]:
    arr = np.asarray(values, dtype=float)
    if arr.shape != (N_JOINTS,):
        raise TaskError(file, fld, f"expected {N_JOINTS} values (one per joint), got {len(values)}", path_id)
    if not np.all(np.isfinite(arr)):
        raise TaskError(file, fld, "values must be finite numbers (no NaN or inf)", path_id)
    return arr


def _limits(file: str, spec: _LimitsSpec | None) -> JointLimits:
    if spec is None:
        return UR16E
    s = _scale(spec.unit)
    out = {}
    for name in ("velocity", "acceleration", "jerk"):
        table = getattr(UR16E, name)
        given = getattr(spec, name)
        if given is None:
            out[name] = table
            continue
        arr = _vector(file, given, f"limits.{name}") * s
        for j in range(N_JOINTS):
            if arr[j] < table[j] * MIN_LIMIT_SHARE:
                raise TaskError(
                    file,
                    f"limits.{name}[{j}]",
                    f"must be at least {MIN_LIMIT_SHARE:g} of the UR16e table "
                    f"({table[j] * MIN_LIMIT_SHARE / s:.6g} {spec.unit}), got {given[j]}",
                )
            if arr[j] > table[j] * (1 + _LIMIT_RTOL):
                raise TaskError(
                    file,
                    f"limits.{name}[{j}]",
                    f"{given[j]} {spec.unit} is above the UR16e table ({table[j] / s:.6g} {spec.unit}); "
                    "a task may only lower limits",
                )
        out[name] = arr
    return JointLimits(position=UR16E.position, **out)


def _path(file: str, spec: _PathSpec, limits: JointLimits) -> PathPlan:
    pid = spec.id
    if not pid or not re.fullmatch(r"[A-Za-z0-9_\-]+", pid):
        raise TaskError(file, "id", f"{pid!r} must be letters, digits, '_' or '-' (it names files and keys)")
    s = _scale(spec.unit)
    if len(spec.waypoints) < 2:
        raise TaskError(file, "waypoints", f"at least 2 waypoints are needed, got {len(spec.waypoints)}", pid)
    rows = [_vector(file, w, f"waypoints[{i}]", pid) for i, w in enumerate(spec.waypoints)]
    wp = np.stack(rows) * s
    for i, j in zip(*np.nonzero(np.abs(wp) > limits.position), strict=True):
        raise TaskError(
            file,
            f"waypoints[{i}][{j}]",
            f"{spec.waypoints[i][j]} {spec.unit} is outside the joint range "
            f"±{limits.position[j] / s:.6g} {spec.unit}",
            pid,
        )
    for i in range(1, len(wp)):
        if np.all(np.abs(wp[i] - wp[i - 1]) < 1e-9):
            raise TaskError(file, f"waypoints[{i}]", "repeats the previous waypoint (use a wait step)", pid)

    def bc(side: str, spec_b: _BoundarySpec) -> list[NDArray[np.float64]]:
        out = []
        for name, lim in (
            ("velocity", limits.velocity),
            ("acceleration", limits.acceleration),
            ("jerk", limits.jerk),
        ):
            given = getattr(spec_b, name)
            if given is None:
                out.append(np.zeros(N_JOINTS))
                continue
            arr = _vector(file, given, f"{side}.{name}", pid) * s
            bad = np.nonzero(np.abs(arr) > lim)[0]
            if bad.size:
                j = int(bad[0])
                raise TaskError(file, f"{side}.{name}[{j}]", f"{given[j]} {spec.unit} is over the limit", pid)
            out.append(arr)
        return out

    v0, a0, j0 = bc("start", spec.start)
    v1, a1, j1 = bc("end", spec.end)
    return PathPlan(pid, wp, Boundary(v0, a0, j0, v1, a1, j1), spec.description)


def _planner(file: str, spec: PlannerSettings) -> PlannerSettings:
    checks = [
        ("n_solutions", 2 <= spec.n_solutions <= MAX_N, f"must be from 2 to {MAX_N}"),
        ("population", 8 <= spec.population <= 10_000, "must be from 8 to 10000"),
        (
            "generations",
            spec.generations is None or 1 <= spec.generations <= 100_000,
            "must be from 1 to 100000",
        ),
        ("seed", 0 <= spec.seed < 2**32, "must be from 0 to 2**32 - 1"),
        (
            "kappa",
            math.isfinite(spec.kappa) and 1.0 < spec.kappa <= 1000.0,
            "must be above 1 and at most 1000",
        ),
    ]
    for name, ok, why in checks:
        if not ok:
            raise TaskError(file, f"planner.{name}", f"{why}, got {getattr(spec, name)}")
    return spec


def _slowest(file: str, path: PathPlan, limits: JointLimits, kappa: float) -> None:
    """The slowest trajectory on the front takes about κ·Σ h_lb (DESIGN §5); no path may take longer
    than any path can (the executor refuses it, and samples grow with it)."""
    h_lb = np.max(np.abs(np.diff(path.waypoints, axis=0)) / limits.velocity, axis=1)
    slowest = kappa * float(h_lb.sum())
    if slowest > MAX_PATH_S:
        raise TaskError(
            file,
            "waypoints",
            f"the slowest trajectory would take about {slowest:.4g} s, over the {MAX_PATH_S:g} s a path may "
            "take: raise the velocity limits or lower planner.kappa",
            path.id,
        )


def _cycle(file: str, steps: list[_StepSpec] | None, paths: dict[str, PathPlan]) -> list[Step]:
    if steps is None:
        return [Step(move=p) for p in paths]
    out = []
    for i, st in enumerate(steps):
        set_fields = [k for k in ("move", "gripper", "wait", "wait_for") if getattr(st, k) is not None]
        if len(set_fields) != 1:
            raise TaskError(
                file,
                f"cycle[{i}]",
                f"a step has exactly one of move, gripper, wait, wait_for; got {set_fields}",
            )
        if st.move is not None and st.move not in paths:
            raise TaskError(file, f"cycle[{i}].move", f"no path with id {st.move!r}")
        if st.wait is not None and not (math.isfinite(st.wait) and 0 <= st.wait <= MAX_WAIT_S):
            raise TaskError(
                file, f"cycle[{i}].wait", f"must be seconds from 0 to {MAX_WAIT_S:g}, got {st.wait}"
            )
        if st.wait_for is not None and not re.fullmatch(r"[A-Za-z0-9_\-]{1,64}", st.wait_for):
            raise TaskError(
                file, f"cycle[{i}].wait_for", f"{st.wait_for!r} must be 1–64 letters, digits, '_' or '-'"
            )
        extra = [k for k in ("deadline", "input", "early") if getattr(st, k) is not None]
        if st.on_late != "wait":
            extra.append("on_late")
        if extra and st.wait_for is None:
            raise TaskError(file, f"cycle[{i}]", f"{', '.join(extra)} belong to a wait_for step")
        if st.deadline is not None and not (math.isfinite(st.deadline) and 0 < st.deadline <= MAX_WAIT_S):
            raise TaskError(
                file, f"cycle[{i}].deadline", f"must be seconds in (0, {MAX_WAIT_S:g}], got {st.deadline}"
            )
        if st.input is not None and not 0 <= st.input <= MAX_INPUT:
            why = f"a UR standard digital input is 0–{MAX_INPUT}, got {st.input}"
            raise TaskError(file, f"cycle[{i}].input", why)
        if st.early is not None and not (math.isfinite(st.early) and 0 < st.early <= MAX_EARLY_S):
            why = f"must be seconds in (0, {MAX_EARLY_S:g}], got {st.early}"
            raise TaskError(file, f"cycle[{i}].early", why)
        out.append(
            Step(st.move, st.gripper, st.wait, st.wait_for, st.deadline, st.on_late, st.input, st.early)
        )
    if not any(s.move for s in out):
        raise TaskError(file, "cycle", "the cycle moves along no path")
    return out


def parse_task(text: str, file: str = "<task>") -> Task:
    """Decode and check a task program; raises ``TaskError`` (one line: file, path, field)."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise TaskError(file, "(syntax)", str(exc)) from exc
    try:
        spec = msgspec.convert(raw, _TaskSpec, strict=True)
    except msgspec.ValidationError as exc:
        raise _translate(file, raw, exc) from exc
    limits = _limits(file, spec.limits)
    paths: dict[str, PathPlan] = {}
    for ps in spec.paths:
        if ps.id in paths:
            raise TaskError(file, "id", "duplicate path id", ps.id)
        paths[ps.id] = _path(file, ps, limits)
    if not paths:
        raise TaskError(file, "paths", "the task has no path")
    planner = _planner(file, spec.planner)
    for p in paths.values():
        _slowest(file, p, limits, planner.kappa)
    return Task(
        name=spec.task.name,
        source=file,
        limits=limits,
        paths=paths,
        cycle=_cycle(file, spec.cycle, paths),
        planner=planner,
        description=spec.task.description,
    )


def load_task(path: str | FsPath) -> Task:
    p = FsPath(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise TaskError(str(p), "(file)", exc.strerror or str(exc)) from exc
    except UnicodeDecodeError as exc:
        raise TaskError(str(p), "(file)", f"not UTF-8 text: {exc.reason}") from exc
    return parse_task(text, str(p))


def continuity_gaps(task: Task) -> list[str]:
    """Where consecutive moves of the cycle do not join (the robot would have to jump), cycle closing.

    Not an error for planning (each path is planned on its own); the executor refuses such a cycle.
    """
    moves = [s.move for s in task.cycle if s.move]
    gaps = []
    for a, b in zip(moves, moves[1:] + moves[:1], strict=True):
        end, start = task.paths[a].waypoints[-1], task.paths[b].waypoints[0]
        err = float(np.max(np.abs(end - start)))
        if err > CONTINUITY_TOL_RAD:
            gaps.append(f"path '{a}' ends {err:.4g} rad away from where '{b}' starts")
    return gaps
