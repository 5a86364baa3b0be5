"""Every service of Cadence, declared once (dora's ``dataflow.yml``: a node's id, its code and its settings
in one place). The graph (schemas/topology.py) says what a role reads and publishes; this says which code
plays it: the node class, its settings, what its unit says it is and adds to the common one, what of the
cell's set-up it needs, whether it is an ECG source (a cell runs one: ``cell``) and whether it plans
before the cell's clock starts (``PLANNER``). From it come ``cadence run``'s list, the settings ``cadence
install`` writes and the demo hands over, the systemd units (``unit``), the demo's launch order
(``launch_order``) and each service's ``NAME``, so a new service is one entry here and one role in the
graph, and a test holds the two against each other. A service's name is spelled here and in the graph
only (tests/schemas/test_graph.py).

Modules are named, not imported: ``cadence --help`` must not load the executor's servo loop or the
planner to list what it can run.
"""

from __future__ import annotations

import contextlib
import importlib
import os
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal

from schemas.topology import ECG_SOURCES
from schemas.topology import SERVICES as GRAPH_SERVICES
from schemas.topology import launch_order as graph_launch_order

if TYPE_CHECKING:
    from common.runtime.node import Node

NETWORK = "AF_UNIX AF_INET AF_INET6 AF_NETLINK"  # Zenoh's sockets, and the interfaces it lists
# What a cell is set up with that a service's settings take (cadence install and the demo fill them in):
# the task program, the robot, the strap, the simulated person, the resting RR where no calibration is,
# the decision's mode, the separation sources
Need = Literal["task", "robot", "strap", "twin", "resting_rr", "decide", "separation"]


@dataclass(frozen=True, slots=True)
class Service:
    name: str  # its role in the graph, its section in cadence.toml, its unit ``cadence-<name>.service``
    node: str  # the node class in ``services/<name>/__main__.py``; "" for a stand-in outside the graph
    description: str  # the unit's ``Description=``
    unit_extra: str = ""  # lines its unit adds after ``ExecStart=`` (the executor's real-time rights)
    realtime: bool = False  # the unit lets the process raise one thread to SCHED_FIFO (DESIGN §11)
    families: str = NETWORK  # ``RestrictAddressFamilies=``
    families_why: str = ""  # a comment above a family that is not obvious
    unit: bool = True  # it runs under systemd on a cell (the UR emulator stands in for a robot: no unit)
    needs: tuple[Need, ...] = ()  # what of the cell's set-up its settings take
    # an ECG source: a cell runs one, the gateway ("strap": a Polar H10 or a replay) or the twin ("twin")
    ecg: Literal["", "strap", "twin"] = ""
    plans_first: bool = False  # it plans what the cell lacks before the cell's clock starts (the store)
    nice: int = 0  # its unit's ``Nice=``: a demo, a bench or a test starting it gives it the same

    def start_as_unit(self) -> None:
        """A ``preexec_fn`` for a process of it started outside systemd: the unit's priority, where this
        user may raise it (else as it is: the run says what it measured with)."""
        if self.nice:
            with contextlib.suppress(OSError):
                os.nice(self.nice)

    @property
    def module_name(self) -> str:
        return f"services.{self.name}.__main__"

    def module(self) -> ModuleType:
        return importlib.import_module(self.module_name)

    def settings(self) -> type[Any]:
        """Its ``[<name>]`` section of cadence.toml."""
        return self.module().Settings

    def node_class(self) -> type[Node]:
        return getattr(self.module(), self.node)

    def run(self, argv: list[str] | None = None) -> int:
        """``cadence run <name>``: the service's own ``run`` (its ``prepare`` checks come with it)."""
        return self.module().run(argv)


GATEWAY = Service(
    "ecg_gateway",
    "EcgGateway",
    "Cadence ECG gateway (a Polar H10 over BLE, or a replay)",
    families_why="# BLE goes through BlueZ on the system D-Bus (AF_UNIX)",
    needs=("strap",),
    ecg="strap",
)
TWIN = Service(
    "operator_twin",
    "OperatorTwin",
    "Cadence operator twin (the simulated co-worker: the ECG of a cell without a strap)",
    families="AF_UNIX AF_INET AF_INET6",
    needs=("twin",),
    ecg="twin",
)
ANALYSER = Service(
    "hrv_analyser", "HrvAnalyser", "Cadence HRV analyser (R peaks, cleaned RR, mean RR windows)"
)
DECIDER = Service(
    "decision_maker", "DecisionMaker", "Cadence decision maker (paper Alg. 1)", needs=("resting_rr", "decide")
)
STORE = Service(
    "pareto_store",
    "ParetoStore",
    "Cadence Pareto store (NSGA-II planning, SQLite)",
    needs=("task",),
    plans_first=True,
)
EXECUTOR = Service(
    "executor",
    "Executor",
    "Cadence executor (500 Hz servo loop; the only service that moves the robot)",
    realtime=True,
    unit_extra="""\
# Real time, for the servo thread only (DESIGN §11): the unit grants the right, the thread raises itself
# with sched_setscheduler; CPUSchedulingPolicy=fifo would make Zenoh's threads FIFO too. Every core but
# core 0 (which takes most interrupts); on any machine with 2 or more cores. The servo thread claims the
# last core no other executor holds (lock files in /run/cadence), or set servo_core; keep that core free
# of other work (isolcpus= or a CPU set) on a line PC.
CPUAffinity=1-1023
RuntimeDirectory=cadence
RuntimeDirectoryPreserve=yes
LimitRTPRIO=90
LimitMEMLOCK=infinity
# Its looks at the person's distance and the ramps they plan, ahead of ordinary work on the host: a reading's
# scale must reach the servo within the adoption budget (docs/robot.md); beside two busy loops, at 0,
# adoptions took up to 0.5 s
Nice=-10
""",
    nice=-10,
    needs=("task", "robot", "separation"),
)
UR_EMULATOR = Service(
    "ur_emulator", "", "Cadence UR controller emulator (RTDE and dashboard: a robot for a cell)", unit=False
)
SERVICES: tuple[Service, ...] = (GATEWAY, TWIN, ANALYSER, DECIDER, STORE, EXECUTOR, UR_EMULATOR)

BY_NAME = {s.name: s for s in SERVICES}
IN_GRAPH = tuple(s for s in SERVICES if s.node)

if {s.name for s in IN_GRAPH} != set(GRAPH_SERVICES):  # one list: a role without code, or code without one
    differ = sorted({s.name for s in IN_GRAPH} ^ set(GRAPH_SERVICES))
    raise ImportError(f"services/registry.py and the graph's services differ: {differ}")
if {s.name for s in SERVICES if s.ecg} != set(ECG_SOURCES):  # the graph's publishers of the ECG
    raise ImportError(f"services/registry.py's ECG sources are not the graph's: {ECG_SOURCES}")
PLANNER = next(s for s in IN_GRAPH if s.plans_first)


def cell(twin: bool) -> tuple[Service, ...]:
    """The graph's services a cell runs: all but one ECG source (the twin's ECG, or the strap's)."""
    return tuple(s for s in IN_GRAPH if s.ecg in ("", "twin" if twin else "strap"))


def launch_order() -> tuple[Service, ...]:
    """The graph's services, each after those it reads from (``schemas.topology.launch_order``)."""
    return tuple(BY_NAME[name] for name in graph_launch_order())


def unit(service: Service, template: str, prefix: str = "/opt/cadence") -> str:
    """Its systemd unit: the common template (deploy/systemd/cadence-service.in) with its own lines."""
    if not service.unit:
        raise ValueError(f"{service.name} has no systemd unit")  # a stand-in runs beside a cell, not in it
    refused = "@privileged @mount @debug @cpu-emulation @obsolete @raw-io @reboot @swap"
    syscalls = (  # real time needs setrlimit and sched_setscheduler, which @resources holds
        f"SystemCallFilter=~{refused}\n"
        if service.realtime
        else f"SystemCallFilter=~{refused.replace('@mount', '@resources @mount')}\n"
        "# NUMA memory policy, which allocators ask for (@resources would forbid it)\n"
        "SystemCallFilter=mbind get_mempolicy set_mempolicy\n"
    )
    families = (
        service.families_why + "\n" if service.families_why else ""
    ) + f"RestrictAddressFamilies={service.families}\n"
    text = template[template.index("\n[Unit]") + 1 :].format(
        name=service.name,
        description=service.description,
        extra=service.unit_extra,
        syscalls=syscalls,
        families=families,
        realtime="" if service.realtime else "RestrictRealtime=yes\n",
    )
    return text.replace("/opt/cadence", prefix)
