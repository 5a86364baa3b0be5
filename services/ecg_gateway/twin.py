"""The ``twin`` source: the simulated operator of common/sim/twin.py, wired to the bus.

It watches the robot (``robot/state``: joint velocities, what the robot waits for; ``robot/cycle``), and
produces what a real worker would: an ECG at 130 Hz for the gateway to publish, the parts the task
waits for (``operator/signal``, after a handling time), and errors (``operator/error``). Data time comes
from the shared clock, so the twin runs at the demo's speed with every other service.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator

import numpy as np

from common.runtime.admission import TimeLine
from common.runtime.bus import Bus, Publisher
from common.runtime.clock import Clock
from common.sim.twin import Operator, TwinParams
from schemas.operator import OperatorError, OperatorSignal
from schemas.robot import CycleReport, RobotState
from schemas.topology import OPERATOR_ERROR, OPERATOR_SIGNAL, ROBOT_CYCLE, ROBOT_STATE
from services.ecg_gateway.sources import CHUNK, FS_HZ, Chunk, EcgSource

log = logging.getLogger("cadence.ecg_gateway")
ROLE = "operator_twin"  # schemas/topology.py: the twin's operator, not the gateway, sends its messages


STATE_AHEAD_S = 10.0
STATE_CONFIRM = 25  # half a second of robot states


class TwinSource(EcgSource):
    name = "twin"

    def __init__(self, params: TwinParams, clock: Clock) -> None:
        self.operator = Operator(params, FS_HZ)
        self.clock = clock
        self.bus: Bus | None = None
        self.signals_out: Publisher[OperatorSignal] | None = None
        self.errors_out: Publisher[OperatorError] | None = None
        self.origin_ns = clock.now_ns()
        self.pending: list[tuple[float, str]] = []  # (data time s, signal): parts being put down
        self.waiting_for: str | None = None
        # robot/state at 50 Hz: one far from the states before it is dropped (common/runtime/admission.py)
        self.line = TimeLine(STATE_AHEAD_S, tolerance_s=0.0, confirm=STATE_CONFIRM)

    def connect(self, bus: Bus) -> None:
        """Open the twin's own ports, as the role the graph gives it (hosted in the gateway's process)."""
        self.bus = bus
        self.signals_out = bus.publisher(OPERATOR_SIGNAL, role=ROLE)
        self.errors_out = bus.publisher(OPERATOR_ERROR, role=ROLE)
        bus.handle(ROBOT_STATE, self.on_state, maxsize=1000, role=ROLE)
        bus.handle(ROBOT_CYCLE, self.on_cycle, role=ROLE)

    def _t(self, t_ns: int) -> float:
        return (t_ns - self.origin_ns) / 1e9

    async def on_state(self, key: str, state: RobotState) -> None:
        verdict = self.line.admit(state.t_ns, state.t_ns, clock_ns=self.clock.now_ns())
        if not verdict.acted_on:
            if self.bus is not None:
                self.bus.reject(key, verdict.code, verdict.detail)
            return
        t = self._t(state.t_ns)
        self.operator.observe(t, np.array(state.qd))
        if state.waiting_for is not None and state.waiting_for != self.waiting_for:
            self.pending.append((t + self.operator.handling_time(), state.waiting_for))
        self.waiting_for = state.waiting_for

    async def on_cycle(self, _: str, report: CycleReport) -> None:
        if self.errors_out is not None and self.operator.makes_error():
            self.errors_out.put(
                OperatorError(
                    t_ns=report.t_ns,
                    seq=self.errors_out.next_seq(),
                    cycle=report.cycle,
                    description=f"simulated (stress {self.operator.stress:.2f})",
                    kind="wrong_object",
                    source="twin",
                )
            )

    def _signals_due(self, t: float) -> None:
        due = [p for p in self.pending if p[0] <= t]
        if not due or self.signals_out is None:
            return
        self.pending = [p for p in self.pending if p[0] > t]
        for when, name in due:
            self.signals_out.put(
                OperatorSignal(
                    t_ns=self.origin_ns + round(when * 1e9),
                    seq=self.signals_out.next_seq(),
                    name=name,
                    source="twin",
                )
            )

    async def chunks(self) -> AsyncIterator[Chunk]:
        i = 0
        while True:
            t0 = i / FS_HZ
            due_ns = self.origin_ns + round(
                (i + CHUNK) * 1e9 / FS_HZ
            )  # a chunk exists once its last sample does
            ahead = (due_ns - self.clock.now_ns()) / 1e9
            await asyncio.sleep(max(0.0, self.clock.wall_s(ahead)))
            x = self.operator.ecg(t0, CHUNK)
            yield Chunk(self.origin_ns + round(t0 * 1e9), np.rint(x).astype(int).tolist())
            self._signals_due(t0 + CHUNK / FS_HZ)
            if i % (CHUNK * 54) == 0:  # about every 30 s of data time
                op = self.operator
                log.info(
                    "twin at %.0f s: exposure %.2f, stress %.2f, mean RR %.3f s, fatigue %.3f",
                    t0,
                    op.exposure(op.t),
                    op.stress,
                    op.mean_rr(),
                    op.fatigue,
                )
            i += CHUNK
