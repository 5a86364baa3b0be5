"""operator_twin: the simulated operator of common/sim/twin.py as a node of the cell (DESIGN §5).

It watches the robot (``robot/state``: joint velocities, what the robot waits for; ``robot/cycle``) and
produces what a real worker with a strap would: an ECG at 130 Hz on ``ecg/samples`` in the ECG gateway's
place, the strap's accelerometer on ``ecg/acc`` (unless ``accelerometer = false``: a strap without one), the
parts the task waits for (``operator/signal``, after a handling time, moving while handling them), and
errors (``operator/error``). With ``away_until_calibrated`` it rests away from the cell until a
calibration at rest is published (``operator/calibration``): the robot waits for its first part meanwhile.
Data time comes from the shared clock, so the twin runs at the demo's speed with every other service. A
robot state far from the states before it is dropped (common/runtime/admission.py).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import AsyncIterator
from typing import Annotated

import msgspec
import numpy as np

from common.runtime.admission import TimeLine
from common.runtime.clock import pause
from common.runtime.node import Node, Out, admitted, every, node_main, on
from common.runtime.service import service_main
from common.sim.twin import ACC_FS_HZ, Operator, TwinParams
from schemas.base import Message
from schemas.ecg import H10_CHUNK as CHUNK
from schemas.ecg import H10_FS_HZ as FS_HZ
from schemas.ecg import AccChunk, EcgChunk
from schemas.operator import Calibration, OperatorError, OperatorSignal, Separation
from schemas.robot import CycleReport, RobotState
from schemas.topology import (
    CALIBRATION,
    ROBOT_CYCLE,
    ROBOT_STATE,
)
from services.registry import TWIN

NAME = TWIN.name
log = logging.getLogger("cadence.operator_twin")
STATE_AHEAD_S = 10.0
STATE_CONFIRM = 25  # half a second of robot states
SIGNAL_AGAIN_S = 1.0  # a part put down is said again this often (data time) while the robot waits for it
# … stamped anew once its stamp is this old: the executor refuses a signal older than its signal_max_age_s
# (60 s by default), and a part that still lies there is a fact about now
SIGNAL_RESTAMP_S = 20.0


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    twin: TwinParams = TwinParams()  # the simulated operator's parameters (common/sim/twin.py)
    separation_period_s: Annotated[float, msgspec.Meta(ge=0.005, le=1.0)] = 0.05  # wall s, as a scanner


class OperatorTwin(Node):
    role = NAME

    async def setup(self) -> None:
        self.operator, self.clock = Operator(self.ctx.settings.twin, FS_HZ), self.ctx.common.clock
        self.origin_ns = self.clock.now_ns()
        self.pending: list[tuple[float, str]] = []  # (data time s, signal): parts being put down
        self.placed: dict[str, tuple[float, float]] = {}  # signal: (when the part was down, last said)
        self.waiting_for: str | None = None
        self.line = TimeLine(STATE_AHEAD_S, confirm=STATE_CONFIRM, skew_s=self.ctx.common.clock_skew_s)

    def ns(self, t_s: float) -> int:
        return self.origin_ns + round(t_s * 1e9)

    @on(ROBOT_STATE, maxsize=1000)
    async def on_state(self, state: RobotState) -> Out:
        admitted(self.line.admit(state.t_ns, state.t_ns, clock_ns=self.clock.now_ns()))
        t = (state.t_ns - self.origin_ns) / 1e9
        self.operator.observe(t, np.array(state.qd))
        if state.waiting_for is not None and state.waiting_for != self.waiting_for and not self.operator.away:
            self.start_handling(t, state.waiting_for)
        self.waiting_for = state.waiting_for
        return self.still_there(t, state.waiting_for)

    def start_handling(self, t: float, part: str) -> None:
        handling = self.operator.handling_time()
        self.operator.handle(t, handling)
        self.pending.append((t + handling, part))

    @on(CALIBRATION)
    async def on_calibration(self, cal: Calibration) -> Out:
        """A calibration at rest taken: the operator comes to the cell (``away_until_calibrated``), and puts
        the part the robot waits for."""
        if self.operator.away and cal.posture == "rest":
            t = max((cal.t_ns - self.origin_ns) / 1e9, self.operator.t)
            self.operator.arrive(t)
            log.info("at the cell from %.0f s (calibrated at rest: RR_r = %.3f s)", t, cal.rr_rest_s)
            if self.waiting_for is not None:
                self.start_handling(t, self.waiting_for)
        return []

    def still_there(self, t: float, waiting_for: str | None) -> Out:
        """A signal is state, not an event (DESIGN §9): a part the robot still waits for is said again,
        with the time it was put down (the same signal: the executor counts it once; anew once that is
        ``SIGNAL_RESTAMP_S`` old), so one lost on the way (a receiver stopped for a while) is not lost for
        good. A part the robot no longer waits for
        is not said again."""
        self.placed = {name: v for name, v in self.placed.items() if name == waiting_for}
        out: list[Message] = []
        for name, (when, said) in self.placed.items():
            if t - said >= SIGNAL_AGAIN_S:
                if t - when >= SIGNAL_RESTAMP_S:  # still there now: a signal is a fact about now
                    when = t
                self.placed[name] = (when, t)
                out.append(OperatorSignal(t_ns=self.ns(when), seq=0, name=name, source="twin"))
        return out

    @on(ROBOT_CYCLE)
    async def on_cycle(self, report: CycleReport) -> Out:
        if not self.operator.makes_error():
            return []
        why = f"simulated (stress {self.operator.stress:.2f})"
        return [OperatorError(t_ns=report.t_ns, seq=0, cycle=report.cycle, description=why,
                              kind="wrong_object", source="twin")]  # fmt: skip

    @every
    async def separation(self) -> Out:
        """As a person tracker would: the distance to the arm now (``to_robot``), at a wall-clock rate (the
        executor judges its age on the wall clock, whatever the demo's speed)."""
        if not self.operator.p.separation:
            return []
        now = self.clock.now_ns()
        d = self.operator.separation((now - self.origin_ns) / 1e9)
        return [Separation(t_ns=now, seq=0, distance_m=d, source="twin", to_robot=True)]

    async def stream(self) -> AsyncIterator[Out]:
        """The ECG, chunk by chunk as the strap sends it (a chunk exists once its last sample does), and
        the parts put down by then."""
        for i in range(0, 2**62, CHUNK):
            ahead_s = (self.ns((i + CHUNK) / FS_HZ) - self.clock.now_ns()) / 1e9
            await pause(max(0.0, self.clock.loop_s(ahead_s)))
            t0, t1 = i / FS_HZ, (i + CHUNK) / FS_HZ
            x = np.rint(self.operator.ecg(t0, CHUNK)).astype(int).tolist()
            out: list[Message] = [EcgChunk(t_ns=self.ns(t0), seq=0, fs_hz=FS_HZ, samples_uv=x, source="twin")]
            if self.operator.p.accelerometer and (acc := self.operator.acc_until(t1)) is not None:
                xyz = acc[1].T.tolist()
                out.append(AccChunk(t_ns=self.ns(acc[0]), seq=0, fs_hz=ACC_FS_HZ,
                                    x_mg=xyz[0], y_mg=xyz[1], z_mg=xyz[2], source="twin"))  # fmt: skip
            for when, name in [p for p in self.pending if p[0] <= t1]:
                out.append(OperatorSignal(t_ns=self.ns(when), seq=0, name=name, source="twin"))
                self.placed[name] = (when, when)
            self.pending = [p for p in self.pending if p[0] > t1]
            self.ctx.counters["chunks"] += 1
            if i % (CHUNK * 54) == 0:  # about every 30 s of data time
                log.info("twin at %.0f s: %s", t0, self.operator)
            yield out


main = node_main(OperatorTwin)


def run(argv: list[str] | None = None) -> int:
    return service_main(NAME, Settings, main, argv)


if __name__ == "__main__":
    sys.exit(run())
