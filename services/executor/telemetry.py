"""What the executor says about the arm, at ``state_rate_hz`` (DESIGN §9): ``robot/state``, and the
controller's buttons as operator signals. A button is a task step's ``input``, a digital input of the
controller; its rising edge is published as any signal is, and the executor counts it when it comes back,
as it would one from elsewhere. Read at the state rate: a press lasts far longer than a state period."""

from __future__ import annotations

from common.runtime.node import Node, Out
from common.safety.states import mode_of
from common.trajectory.task import Task
from schemas.operator import OperatorSignal
from schemas.robot import RobotState
from services.executor.backends import Backend
from services.executor.cycles import Cycles
from services.executor.supervisor import Supervisor


class Telemetry:
    def __init__(self, node: Node, backend: Backend, task: Task) -> None:
        self.node, self.backend = node, backend
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
                self.node.ctx.counters["buttons"] += 1
                out.append(OperatorSignal(t_ns=t_ns, seq=0, name=name, source=f"ur DI{n}"))
        return out

    def sample(self, safety: Supervisor, cycles: Cycles) -> Out:
        t_ns = self.node.ctx.common.clock.now_ns()
        pressed = self.pressed(t_ns)
        b, m = self.backend, safety.motion
        near = cycles.reactions.shown_m() if cycles.reactions.on else None
        state = RobotState(
            t_ns=t_ns,
            seq=0,
            q=b.actual_q().tolist(),
            qd=b.actual_qd().tolist(),
            tcp=b.tcp_pose().tolist(),
            path_id=safety.path_id,
            k=cycles.k,
            mode=mode_of(m.state),
            waiting_for=cycles.waiting_for,
            state=m.state,
            reason=m.reason[:4000],
            scale=min(1.0, max(0.0, float(cycles.reactions.scale_now()))),
            separation_m=None if near is None else min(100.0, round(float(near), 4)),  # to 0.1 mm: S − C + C
        )
        return [*pressed, state]
