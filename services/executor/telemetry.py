"""What the executor says about the arm, at ``state_rate_hz`` (DESIGN §9): ``robot/state``, and the
controller's buttons as operator signals. A button is a task step's ``input``, a digital input of the
controller; its rising edge is published as any signal is, and the executor counts it when it comes back,
as it would one from elsewhere. Read at the state rate: a press lasts far longer than a state period."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from common.runtime.node import Out
from common.safety.states import Motion, mode_of
from common.trajectory.task import Task
from schemas.operator import OperatorSignal
from schemas.robot import RobotState
from services.executor.backends import Backend
from services.executor.kit import Kit


@dataclass(frozen=True, slots=True)
class Snapshot:
    """What the other parts say of the arm at one instant, taken together (the node's ``snapshot``)."""

    motion: Motion  # the safety state and why
    path_id: str | None
    k: int | None
    waiting_for: str | None
    scale: float  # σ now
    separation_m: float | None  # S of the nearest reading, as a person reads it; None when not watched
    selection_seq: int | None = None  # the seq of the selection in force: the decision maker numbers after it


class Telemetry:
    """Owns only the controller's buttons' last state; reads the rest as one ``Snapshot``."""

    def __init__(self, kit: Kit, backend: Backend, task: Task, snapshot: Callable[[], Snapshot]) -> None:
        self.kit, self.backend, self.snapshot = kit, backend, snapshot
        self.buttons = {s.input: s.wait_for for s in task.cycle if s.input is not None and s.wait_for}
        self._inputs = 0

    def pressed(self, t_ns: int) -> list[OperatorSignal]:
        if not self.buttons:
            return []
        now = self.backend.digital_inputs()
        rising, self._inputs = now & ~self._inputs, now
        out = []
        for n, name in self.buttons.items():
            if rising >> n & 1:
                self.kit.counters["buttons"] += 1
                out.append(OperatorSignal(t_ns=t_ns, seq=0, name=name, source=f"ur DI{n}"))
        return out

    def sample(self) -> Out:
        t_ns = self.kit.clock.now_ns()
        pressed = self.pressed(t_ns)
        b = self.backend
        if not b.measured():  # no measure of the arm now: no state (a stale speed is not the arm's)
            self.kit.counters["states_unmeasured"] += 1
            return list(pressed)
        now = self.snapshot()
        m, near = now.motion, now.separation_m
        state = RobotState(
            t_ns=t_ns,
            seq=0,
            q=b.actual_q().tolist(),
            qd=b.actual_qd().tolist(),
            tcp=b.tcp_pose().tolist(),
            path_id=now.path_id,
            k=now.k,
            mode=mode_of(m.state),
            waiting_for=now.waiting_for,
            state=m.state,
            reason=m.reason[:4000],
            scale=min(1.0, max(0.0, float(now.scale))),
            separation_m=None if near is None else min(100.0, round(float(near), 4)),  # to 0.1 mm: S − C + C
            selection_seq=now.selection_seq,
        )
        return [*pressed, state]
