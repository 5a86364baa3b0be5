"""The executor's robots behind one interface (DESIGN §8): ``sim``, a simulated UR16e (common/sim/arm.py),
and ``ur_rtde``, a UR16e (or URSim, or the emulator) through the real ``ur-rtde`` client.

``servo``, ``brake`` and ``settled`` run inside the servo loop; the rest runs outside it, in a worker
thread of the service (they block: connecting waits for the controller).
"""

from __future__ import annotations

import contextlib
import copy
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, cast

import numpy as np
from numpy.typing import NDArray

from common.robot.ur16e import DT, UR16E, JointLimits, forward_kinematics
from common.runtime.errors import CadenceError, ConfigError
from common.sim.arm import SimArm, move_j_profile
from common.trajectory.task import Task
from services.executor.settings import Settings

Array = NDArray[np.float64]
CLOSE_WAIT_S = 30.0  # s: a call in flight (a benchmark's moveJ, slow and short) ends well within it
AT_REST = 1e-4  # rad/s: a joint speed the sim's watchdog takes for an arm at rest


class RobotUnavailable(CadenceError):
    """The robot (or its controller) cannot be reached; the message names where."""


class Backend(Protocol):
    """What the executor needs of a robot controller, whichever it is; the backend owns the link to it."""

    name: str
    realtime: bool  # a controller paces the samples on the wall clock (a stalled executor must stop it)

    def connect(self) -> None: ...
    def close(self) -> None: ...
    def actual_q(self) -> Array: ...
    def actual_qd(self) -> Array: ...
    def tcp_pose(self) -> Array: ...
    def fault(self) -> str: ...  # "" while the arm may move; else why not (protective stop, lost link)
    def link_lost(self) -> bool: ...  # the controller cannot be reached (reconnect() may bring it back)
    def reconnect(self) -> None: ...  # restore the link only; a protective stop stays
    def reset_fault(self) -> None: ...  # a person's resume: unlock a protective stop, restart control
    def prepare(self, q: Array) -> Sequence[object]: ...  # the targets in the form servo takes
    def target(self, q: Array) -> object: ...  # one row in that form, touching nothing (the servo thread's)
    def servo(self, target: object) -> bool: ...
    def brake(self) -> bool: ...
    def settled(self, target: object) -> bool: ...
    def move_j(self, q: Array, speed: float, acceleration: float) -> bool: ...  # the benchmark's, blocking
    def motion_ended(self) -> None: ...  # after a servo motion, whatever its outcome
    def set_gripper(self, on: bool) -> None: ...
    def digital_inputs(self) -> int: ...  # the standard digital inputs 0–7 as bits (the cell's buttons)
    # False where the state read is not the arm as it is now (remote.py: a servo process starved past its
    # controller's watchdog, the arm last seen moving); read in the process that steps it, always True
    def measured(self) -> bool: ...


class SimBackend:
    """The simulated UR16e. Its time is the servo loop's: one controller step per target sent, so at
    ``speed`` X the arm moves X times faster than real time, exactly as far per step.

    Where a person's separation is watched in real time it has a UR controller's watchdog
    (``watchdog_s``; none in a lockstep cell, whose time waits for its servo, nor where no person is
    watched, nor in a cell sped up, which no controller runs: the process demo at 16× on a loaded host
    was silent past 0.1 s, and a stop latched until a person's resume ended its cycles). Once a servo
    motion has begun, targets that stop coming for longer than that mean the controller stopped the arm.
    A frozen arm that keeps its speed does not exist: without the watchdog, a starved executor (its servo
    thread and all) left the arm standing mid-motion while a person walked in, and the loop then caught
    the lost steps up at once, the lease's stop among them, while a state read in between showed an arm
    at speed beside the person. Now the braking stop is taken as the controller would have taken it
    during the silence, the arm is in a protective stop that a resume clears, and a state read while the
    servo thread is still starved already shows the arm where that stop leaves it, at rest. A shorter
    silence is caught up by the loop (services/executor/servo.py)."""

    name = "sim"
    realtime = False  # its time is the samples sent: the loop catches up short stalls (servo.ServoLoop)

    def __init__(
        self,
        q0: Array,
        *,
        lookahead: float = 0.1,
        gain: float = 300.0,
        stop_deceleration: float = 4.0,
        settle_tol: float = 1e-4,
        speed: float = 1.0,
        limits: JointLimits = UR16E,
        gripper_output: int = 0,
        watchdog_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.arm = SimArm(q0, limits)
        self.lookahead, self.gain = lookahead, gain
        self.stop_deceleration, self.settle_tol = stop_deceleration, settle_tol
        self.speed = speed
        self.gripper_output = gripper_output
        self.watchdog_s, self.clock = watchdog_s, clock
        self._kicked: float | None = None  # the last target's time, from a motion's first until its end

    def connect(self) -> None:
        pass

    def close(self) -> None:
        pass

    def _silent_s(self, now: float) -> float:
        """How long past the watchdog's period the targets have been silent at ``now``; ≤ 0 while it
        holds, or while the arm is at rest (held on its path: a silence then stops nothing)."""
        if self.watchdog_s is None or self._kicked is None or float(np.abs(self.arm.qd).max()) <= AT_REST:
            return 0.0
        return now - self._kicked - self.watchdog_s

    def _kick(self) -> bool:
        """The servo thread's call at each step: False once the watchdog has stopped the arm."""
        now = self.clock()
        if self._silent_s(now) > 0.0:
            silent = now - cast(float, self._kicked)
            self._kicked = None
            self.arm.halt(self.stop_deceleration)
            self.arm.protect(
                f"the controller's watchdog: no target for {silent:.3f} s (the executor stalled); "
                "the arm stopped"
            )
            return False
        self._kicked = now
        return True

    def _seen(self) -> SimArm:
        """The arm as a state read sees it: where the watchdog's stop leaves it once the targets have
        been silent past its period, though the starved servo thread has not yet taken that stop."""
        if self._silent_s(self.clock()) <= 0.0:
            return self.arm
        ghost = copy.deepcopy(self.arm)  # a read during a stall, not a servo step: it may allocate
        ghost.halt(self.stop_deceleration)
        return ghost

    def actual_q(self) -> Array:
        return self._seen().q.copy()

    def actual_qd(self) -> Array:
        return self._seen().qd.copy()

    def tcp_pose(self) -> Array:
        return forward_kinematics(self._seen().q.copy())

    def fault(self) -> str:
        return self.arm.fault

    def link_lost(self) -> bool:
        return False

    def reconnect(self) -> None:
        pass

    def reset_fault(self) -> None:
        self.arm.unlock()

    def prepare(self, q: Array) -> Sequence[object]:
        return list(np.ascontiguousarray(q, dtype=float))  # row views: indexing allocates nothing

    def target(self, q: Array) -> object:
        return q

    def servo(self, target: object) -> bool:
        if not self._kick():
            return False
        return self.arm.servo(cast(Array, target), self.lookahead, self.gain)  # what prepare gave: a row

    def brake(self) -> bool:
        if not self._kick():  # the watchdog's stop came first: at rest
            return True
        return self.arm.brake(self.stop_deceleration)

    def settled(self, target: object) -> bool:
        return float(np.max(np.abs(np.asarray(target) - self.arm.q))) <= self.settle_tol

    def move_j(self, q: Array, speed: float, acceleration: float) -> bool:
        for row in move_j_profile(self.arm.q, q, speed, acceleration):
            if not self.arm.jump_to(row):
                return False
            time.sleep(DT / self.speed)
        self.arm.rest()
        return True

    def motion_ended(self) -> None:
        self._kicked = None  # between motions nothing sends: the watchdog is off
        self.arm.rest()

    def digital_inputs(self) -> int:
        return self.arm.digital_in

    def measured(self) -> bool:
        return True

    def set_gripper(self, on: bool) -> None:
        bit = 1 << self.gripper_output
        self.arm.digital_out = (self.arm.digital_out | bit) if on else (self.arm.digital_out & ~bit)


def _until_not(holds: Callable[[], bool], within_s: float, every_s: float) -> bool:
    """Ask ``holds`` every ``every_s`` until it is false or ``within_s`` passed: True if it still holds."""
    deadline = time.monotonic() + within_s
    while (still := holds()) and time.monotonic() < deadline:
        time.sleep(every_s)
    return still


class Dashboard:
    """A UR controller's dashboard server (port 29999): what a person does at the pendant, answered whatever
    the RTDE link and the control script do (a protective stop holds both down)."""

    def __init__(self, host: str) -> None:
        self.host = host

    def _exchange(self, act: Callable[[Any], object]) -> object:
        import dashboard_client

        dash = dashboard_client.DashboardClient(self.host)
        try:
            dash.connect()
            return act(dash)
        except RuntimeError as exc:
            raise RobotUnavailable(f"UR dashboard at {self.host}: {exc}") from None
        finally:
            with contextlib.suppress(RuntimeError):
                dash.disconnect()

    def unlock(self) -> None:
        """Unlock a protective stop and close the pop-up."""
        self._exchange(lambda dash: (dash.unlockProtectiveStop(), dash.closeSafetyPopup()))

    def protective_stop(self) -> bool:
        """The dashboard's word on it; False when the dashboard cannot be asked either."""
        try:
            return "PROTECTIVE_STOP" in str(self._exchange(lambda dash: dash.safetystatus()))
        except RobotUnavailable:
            return False


def gone(host: str, armed: bool) -> str:
    """A controller not reached: during an armed motion (its watchdog) it was lost, whichever of the
    client's interfaces said so first (servoJ refusing, or the receive interface's EOF)."""
    return f"the controller at {host}: {'lost during motion' if armed else 'not connected'}"


class UrRtdeBackend:
    """A UR e-Series controller through ``ur-rtde==1.6.5``: servoJ at 500 Hz, the watchdog kicked every
    tick (the controller stops the arm if the executor stalls), servoStop to brake, moveJ for the bench
    (the executor moves to a path's start on the servo loop), a digital output for the gripper. Three
    threads call into the client: the servo loop, the service's worker threads (a reconnect, the
    watchdog's arming) and its event loop (the state, the fault). ur-rtde does not guard an interface
    against its own ``disconnect``: a servoJ in flight while another thread disconnects crashed the whole
    process (SIGSEGV, in CI). So every call goes through ``_using``, and ``close`` tears the interfaces
    down only once no call is in flight; a call that comes meanwhile finds no link."""

    name = "ur_rtde"
    realtime = True

    def __init__(
        self,
        host: str,
        *,
        lookahead: float = 0.1,
        gain: float = 300.0,
        stop_deceleration: float = 4.0,
        settle_tol: float = 1e-3,
        watchdog_hz: float = 10.0,
        gripper_output: int = 0,
    ) -> None:
        if not 0.03 <= lookahead <= 0.2 or not 100 <= gain <= 2000:
            raise ValueError(f"servoJ takes lookahead 0.03–0.2 s and gain 100–2000, got {lookahead}, {gain}")
        self.host, self.lookahead, self.gain = host, lookahead, gain
        self.stop_deceleration, self.settle_tol = stop_deceleration, settle_tol
        self.watchdog_hz, self.gripper_output = watchdog_hz, gripper_output
        self._c: Any = None  # ur_rtde ships no type information
        self._r: Any = None
        self._lost, self._watchdog = "", False
        self._last = {"q": np.zeros(6), "qd": np.zeros(6), "tcp": np.zeros(6)}
        self._inputs = 0
        self._io = threading.Condition()
        self._in_flight = 0  # calls into the interfaces now
        self._closing = False
        self.dashboard = Dashboard(host)

    @contextlib.contextmanager
    def _using(self) -> Iterator[tuple[Any, Any] | None]:
        """The (control, receive) interfaces for one call, kept from ``close`` until it returns; None
        while they are being torn down or are gone."""
        with self._io:
            if self._closing or self._c is None or self._r is None:
                ifaces = None
            else:
                ifaces = (self._c, self._r)
                self._in_flight += 1
        try:
            yield ifaces
        finally:
            if ifaces is not None:
                with self._io:
                    self._in_flight -= 1
                    self._io.notify_all()

    def connect(self) -> None:
        import rtde_control
        import rtde_receive

        try:
            self._r = rtde_receive.RTDEReceiveInterface(self.host, 500.0)
            self._c = rtde_control.RTDEControlInterface(self.host, 500.0)
        except RuntimeError as exc:
            self.close()
            if self.dashboard.protective_stop():  # the script cannot run until the stop is unlocked
                raise RobotUnavailable(
                    f"UR controller at {self.host} is in a protective stop, so its control script cannot "
                    "start: `cadence robot resume` unlocks it (or unlock it on the pendant)"
                ) from None
            raise RobotUnavailable(f"UR controller at {self.host}: {exc}") from None
        self._lost = ""
        self._watchdog = False

    def close(self) -> None:
        """Waits for the calls in flight (a benchmark's moveJ runs to its end) before disconnecting."""
        with self._io:
            self._closing = True
            if not self._io.wait_for(lambda: self._in_flight == 0, timeout=CLOSE_WAIT_S):
                self._closing = False
                raise RobotUnavailable(
                    f"UR controller at {self.host}: a call into the client has not returned for "
                    f"{CLOSE_WAIT_S:.0f} s; the link is left as it is"
                )
            ifaces, self._c, self._r = (self._c, self._r), None, None
        try:
            for iface in ifaces:
                if iface is not None:
                    with contextlib.suppress(RuntimeError):
                        iface.disconnect()
        finally:
            with self._io:
                self._closing = False

    def _read(self, name: str, getter: str) -> Array:
        """The receive interface's latest value; while it reconnects (None, or a dead link), the last
        value read, so the state publisher never fails on a reconnect."""
        with self._using() as ifaces:
            if ifaces is not None:
                with contextlib.suppress(RuntimeError):
                    self._last[name] = np.array(getattr(ifaces[1], getter)())
        return self._last[name].copy()

    def actual_q(self) -> Array:
        return self._read("q", "getActualQ")

    def actual_qd(self) -> Array:
        return self._read("qd", "getActualQd")

    def tcp_pose(self) -> Array:
        return self._read("tcp", "getActualTCPPose")

    def fault(self) -> str:
        with self._using() as ifaces:
            if self._lost or ifaces is None or not ifaces[0].isConnected():
                return self._lost or gone(self.host, self._watchdog)
            c, r = ifaces
            if r.isProtectiveStopped():
                return "protective stop"
            if r.isEmergencyStopped():
                return "emergency stop"
            if not c.isProgramRunning():
                return "the control script stopped on the controller (its watchdog, or a stop there)"
            return ""

    def link_lost(self) -> bool:
        with self._using() as ifaces:
            return bool(self._lost) or ifaces is None or not ifaces[0].isConnected()

    def reconnect(self) -> None:
        self.close()
        self.connect()

    def reset_fault(self) -> None:
        """What a person does at the pendant after a protective stop, through the dashboard: unlock it and
        close the safety pop-up; then the control script is started again (a reconnect uploads it). The
        controller refuses an unlock within 5 s of the stop: that is a ``RobotUnavailable`` with its words,
        and the robot stays stopped. Without an RTDE link, a protective stop is unlocked through the
        dashboard all the same (it holds the link down: no control script runs while it lasts); with none,
        ``RobotUnavailable`` says the executor is reconnecting."""
        if self.link_lost():
            # a controller in a protective stop runs no control script, so the link cannot come back
            # until the stop is unlocked: the dashboard needs no RTDE link (a watchdog trip, then a stop)
            if not self.dashboard.protective_stop():
                raise RobotUnavailable(
                    f"not connected to the controller at {self.host} ({self.fault()}); the executor "
                    "reconnects by itself: resume again once it says it is connected"
                )
            self.dashboard.unlock()
            _until_not(self.dashboard.protective_stop, 1.0, 0.05)
            self.reconnect()
            return
        with self._using() as ifaces:
            r = ifaces[1] if ifaces is not None else None
            if r is not None and r.isConnected() and r.isProtectiveStopped():
                self.dashboard.unlock()
                # the receive interface sees the release a tick or two later
                if _until_not(r.isProtectiveStopped, 1.0, 0.01):
                    raise RobotUnavailable(f"the controller at {self.host} kept its protective stop")
        self.reconnect()

    def prepare(self, q: Array) -> Sequence[object]:
        """Also arms the controller's watchdog: from here on the servo loop kicks it every tick, and the
        controller stops the program if the kicks stop (the executor stalled or died). Without a link it
        arms nothing: the motion's first servo call finds the link lost, and that is its fault."""
        with self._using() as ifaces:
            if not self._watchdog and ifaces is not None and not self._lost:
                try:
                    ifaces[0].setWatchdog(self.watchdog_hz)
                    self._watchdog = True
                except RuntimeError:
                    self._lost = "connection to the controller lost before the motion"
        return np.asarray(q, dtype=float).tolist()

    def target(self, q: Array) -> object:
        return q.tolist()

    def servo(self, target: object) -> bool:
        # The receive interface sees a vanished controller at once (its reader thread gets EOF). Asking
        # the control interface then would enter its own reconnect, which blocks inside the call for
        # seconds: this check keeps the servo thread out of it.
        with self._using() as ifaces:
            if self._lost or ifaces is None or not ifaces[1].isConnected():
                self._lost = self._lost or "connection to the controller lost during motion"
                return False
            try:
                ok = ifaces[0].servoJ(target, 0.0, 0.0, DT, self.lookahead, self.gain)
                ifaces[0].kickWatchdog()
            except RuntimeError:
                self._lost = "connection to the controller lost during motion"
                return False
            return bool(ok)

    def brake(self) -> bool:
        with self._using() as ifaces:
            if self._lost or ifaces is None or not ifaces[1].isConnected():
                return True  # nothing to tell a controller that is gone
            try:
                ifaces[0].servoStop(self.stop_deceleration)
            except RuntimeError:
                self._lost = "connection to the controller lost while stopping"
            return True  # the controller decelerates on its own

    def settled(self, target: object) -> bool:
        return float(np.max(np.abs(np.asarray(target) - self.actual_q()))) <= self.settle_tol

    def motion_ended(self) -> None:
        """Disarms the watchdog: between motions (gripper, waits) nothing kicks it, and the robot is at
        rest; ``prepare`` arms it again. A controller gone now was lost by the motion: kept so."""
        with self._using() as ifaces:
            if self._watchdog and not self._lost and (ifaces is None or not ifaces[0].isConnected()):
                self._lost = gone(self.host, True)
            elif self._watchdog and not self._lost and ifaces is not None:
                with contextlib.suppress(RuntimeError):
                    ifaces[0].setWatchdog(0.0)
        self._watchdog = False

    def move_j(self, q: Array, speed: float, acceleration: float) -> bool:
        """False, not moved, without a link."""
        self.motion_ended()  # nothing kicks the watchdog during a blocking moveJ
        with self._using() as ifaces:
            return ifaces is not None and bool(
                ifaces[0].moveJ(np.asarray(q, float).tolist(), speed, acceleration)
            )

    def measured(self) -> bool:
        return True

    def digital_inputs(self) -> int:
        with self._using() as ifaces, contextlib.suppress(RuntimeError):
            if ifaces is not None:
                self._inputs = int(ifaces[1].getActualDigitalInputBits()) & 0xFF
        return self._inputs

    def set_gripper(self, on: bool) -> None:
        """Through an IO interface opened for this call only: ur-rtde 1.6.5's RTDEIOInterface ends the
        whole process (an uncaught exception in its reader thread) when the controller's connection
        drops while it is open. The receive and control interfaces survive that, so only they stay
        connected."""
        import rtde_io

        try:
            io = rtde_io.RTDEIOInterface(self.host)
        except RuntimeError as exc:
            raise RobotUnavailable(f"UR controller at {self.host} (IO interface): {exc}") from None
        try:
            io.setStandardDigitalOut(self.gripper_output, on)
        finally:
            io.disconnect()


def backend_for(settings: Settings, task: Task, speed: float, q0: Sequence[float] | None = None) -> Backend:
    """The configured backend, not yet connected; a setting it cannot take is a ConfigError at start.
    ``q0``: where a sim arm stands (a servo process restarted: where the last one left it)."""
    if settings.backend == "ur_rtde":
        if speed != 1.0:
            raise ConfigError(f"[executor] backend: a real controller runs at speed 1, not {speed}")
        try:
            return UrRtdeBackend(
                settings.host,
                lookahead=settings.lookahead_s,
                gain=settings.gain,
                stop_deceleration=settings.stop_deceleration,
                watchdog_hz=settings.watchdog_hz,
                gripper_output=settings.gripper_output,
            )
        except ValueError as exc:
            raise ConfigError(f"[executor] {exc}") from None
    first = next(s.move for s in task.cycle if s.move is not None)
    start = (
        np.asarray(q0, dtype=float)
        if q0 is not None
        else np.radians(settings.sim_start_deg)
        if settings.sim_start_deg is not None
        else task.paths[first].waypoints[0]
    )
    if len(start) != 6:
        raise ConfigError(f"[executor] sim_start_deg: 6 joint angles, got {len(start)}")
    return SimBackend(
        start,
        lookahead=settings.lookahead_s,
        gain=settings.gain,
        stop_deceleration=settings.stop_deceleration,
        speed=speed,
        limits=task.limits,
        gripper_output=settings.gripper_output,
        watchdog_s=1.0 / settings.watchdog_hz if settings.separation and speed == 1.0 else None,
    )
