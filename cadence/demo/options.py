"""What a demo is asked (``cadence demo``'s options) and what it hands each service: the settings a
deployment config's tables would hold, from what each service needs of the cell (services/registry.py),
and the order the cell starts in."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from common.runtime.resources import EXAMPLE_TASK
from common.sim.twin import TwinParams
from services.registry import Need, cell, launch_order

DEMO_TOLERANCE = 0.7  # the twin's (common/sim/twin.py: 0.8 by default)


# from the registry and its graph: readers before writers, answerers before askers; the twin sends the
# ECG, no gateway runs
ORDER = tuple(s.name for s in launch_order() if s in cell(twin=True))


@dataclass(frozen=True, slots=True)
class DemoOptions:
    duration_s: float = 600.0  # data time
    speed: float = 8.0
    out: Path = Path("demo-out")
    seed: int = 1
    task: Path = EXAMPLE_TASK
    kill: tuple[tuple[str, float], ...] = ()  # (service, data time s): SIGKILL it then
    live: bool = True
    listen: str | None = None  # the router's endpoint; a free loopback port when None
    twin: tuple[tuple[str, bool | int | float], ...] = ()  # TwinParams fields over the demo's own
    decide: str = "paper"  # the decision maker's mode: "paper" (Alg. 1) or "personal" (DESIGN §7)
    processes: bool = False  # every service its own process on the wall clock (processes.py), not lockstep


TWIN_SOURCE = '[{ name = "twin", detects = "body", to_robot = true }]'


def twin_table(opts: DemoOptions) -> dict[str, bool | int | float]:
    """The twin's parameters in the demo: its seed, a co-worker less tolerant than the default, and what
    ``--twin`` asks."""
    return {"seed": opts.seed, "tolerance": DEMO_TOLERANCE, **dict(opts.twin)}


def inline_toml(table: dict[str, bool | int | float]) -> str:
    def value(v: bool | int | float) -> str:
        return ("true" if v else "false") if isinstance(v, bool) else repr(v)

    return "{ " + ", ".join(f"{k} = {value(v)}" for k, v in table.items()) + " }"


def demo_settings(opts: DemoOptions) -> dict[str, dict[str, str]]:
    """Each service's settings in the demo beyond its built-in defaults, as a deployment config's
    ``[service]`` tables would hold them (values in TOML; a bare word is a string): what it needs of the
    cell (services/registry.py), given as the demo's cell has it."""
    twin = twin_table(opts)
    given: dict[Need, dict[str, str]] = {
        "task": {"task": str(opts.task)},
        "resting_rr": {"rr_rest_s": repr(TwinParams().rr_rest_s)},
        "decide": {"decide": opts.decide},
        # a co-worker less tolerant than the twin's default: the example task's waits for the operator
        # (B2 clear, the parts) leave the arm idle part of each cycle, and the demo should show Alg. 1 at
        # work, stress first and relief after, within its first minutes
        "twin": {"twin": inline_toml(twin)},
        "strap": {},  # no strap: the twin is the cell's ECG source
        # no person stands at a pendant: a stop (the sim's watchdog on a loaded host) resumes by itself,
        # said in the events, rather than ending the demo's cycles until `cadence robot resume`
        "robot": {"backend": "sim", "start_selection": "last", "resume_policy": "auto"},
        # the twin walks into the shared area now and then: speed and separation monitoring, unless the
        # twin is told to publish no distance (then nothing would free the arm); the twin is the cell's
        # one source: a tracker that sees the body and measures to the arm
        "separation": {
            "separation": "true" if twin.get("separation", True) else "false",
            "separation_sources": TWIN_SOURCE,
        },
    }
    return {s.name: {k: v for need in s.needs for k, v in given[need].items()} for s in cell(twin=True)}
