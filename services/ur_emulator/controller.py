"""The emulated UR controller's state: the arm (common/sim/arm.py, the same model as the executor's sim
backend), the registers RTDE reads and writes, and the control script the ur-rtde client uploads, run
once per 2 ms tick the way shared/reference/ur-rtde-wire.md describes it:

- command 0 (clear) → ready (output_int_register_0 = 1);
- a realtime command (servoJ, …) → applied at once, ready;
- any other command → run once, done (= 2) when finished (stopJ and servoStop after decelerating,
  moveJ at the end of its motion);
- 255 → the program ends (runtime_state STOPPED).

A limit violation is a protective stop, as on the real arm: safety mode 3, the protective-stop bit in
safety_status_bits, the program stopped. A watchdog (setWatchdog) stops the program when the kicks stop.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from common.robot.ur16e import DT, forward_kinematics
from common.sim.arm import SimArm, move_j_profile

STOPPED, PLAYING = 1, 2
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
JOINT_MODE_RUNNING = 253

SERVOJ, SERVOSTOP, STOPJ, MOVEJ, SET_WATCHDOG, STOP_SCRIPT = 11, 16, 34, 1, 35, 255
REALTIME = {11, 24, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
CMD_REGISTER = 0  # input_int_register_0 (24 with the client's upper-range flag)
UNLOCK_AFTER_S = 5.0  # the dashboard refuses to unlock a protective stop sooner


class Controller:
    def __init__(self, q0: np.ndarray) -> None:
        self.lock = threading.RLock()
        self.arm = SimArm(q0)
        self.started = time.monotonic()
        self.runtime_state = STOPPED
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48
        self.digital_out = 0
        self.digital_in = 0  # standard digital inputs, a bit each: set with `di N 1` on the emulator's stdin
        self.watchdog_hz = 0.0
        self.last_kick = 0.0
        self._running: int | None = None  # the non-realtime command being run
        self._profile: np.ndarray | None = None
        self._profile_i = 0
        self._brake = 0.0
        self._mask = 0xFF
        self.servo: tuple[np.ndarray, float, float] | None = None  # target, lookahead, gain while servoing
        self.log: list[str] = []  # what happened, for the operator's terminal and the tests
        self.fault_since = 0.0  # when the current protective stop began (monotonic)
        self._faulted = False

    # --- from the sockets ---------------------------------------------------------------------------

    def load_script(self, text: str) -> None:
        with self.lock:
            self.runtime_state = PLAYING
            self._running = None
            self.watchdog_hz = 0.0
            self.log.append(f"script uploaded ({len(text)} bytes), program running")

    def write_inputs(self, recipe: int, fields: dict[str, Any], control: bool) -> None:
        """An RTDE input package: register values by name. The watchdog watches the command register
        (URScript's rtde_set_watchdog is per variable): any package that writes it is a kick, which is
        what kickWatchdog sends (0, on recipe 11). A servoJ's target is taken as it arrives: the script's
        servo thread keeps tracking the latest target until another command ends servoing, whatever the
        command register holds meanwhile."""
        with self.lock:
            if control and "input_int_register_0" in fields:
                self.last_kick = time.monotonic()
            for name, value in fields.items():
                if name.startswith("input_int_register_"):
                    self.in_int[int(name.rsplit("_", 1)[1])] = int(value)
                elif name.startswith("input_double_register_"):
                    self.in_double[int(name.rsplit("_", 1)[1])] = float(value)
                elif name == "standard_digital_output_mask":
                    self._mask = int(value)
                elif name == "standard_digital_output":
                    self.digital_out = (self.digital_out & ~self._mask) | (int(value) & self._mask)
            if control and fields.get("input_int_register_0") == SERVOJ:
                d = self.in_double
                self.servo = (np.array(d[0:6]), d[9] or 0.1, d[10] or 300.0)

    def dashboard(self, line: str) -> str:
        cmd = line.strip()
        with self.lock:
            if cmd == "PolyscopeVersion":
                return "URSoftware 5.15.0.0 (Jan 01 2024)"
            if cmd == "get serial number":
                return "20235500001"
            if cmd == "is in remote control":
                return "true"
            if cmd == "stop":
                self._end_program("stopped from the dashboard")
                return "Stopped"
            if cmd == "unlock protective stop":
                # as the real controller: not within 5 s of the stop, to make a person look first
                if self.arm.fault and time.monotonic() - self.fault_since < UNLOCK_AFTER_S:
                    return (
                        "Cannot unlock protective stop until 5s after occurrence. "
                        "Always inspect cause of protective stop before unlocking"
                    )
                self.arm.unlock()
                return "Protective stop releasing"
            if cmd == "close safety popup":
                return "closing safety popup"
            if cmd == "safetystatus":
                return "Safetystatus: PROTECTIVE_STOP" if self.arm.fault else "Safetystatus: NORMAL"
            if cmd == "programState":
                return "PLAYING" if self.runtime_state == PLAYING else "STOPPED"
            if cmd == "robotmode":
                return "Robotmode: RUNNING"
        return f"could not understand: '{cmd}'"

    def emergency_stop(self) -> None:
        """The e-stop pressed (and released): the program ends and the arm brakes at once."""
        with self.lock:
            self._end_program("emergency stop")
            self._brake = 8.0

    def bump(self) -> None:
        """Something hit the arm (SIGUSR1): a protective stop, as the force limit gives on the real one."""
        with self.lock:
            self.arm.protect("external force over the limit (a collision)")

    # --- the 2 ms tick ------------------------------------------------------------------------------

    def tick(self) -> None:
        with self.lock:
            if self.arm.fault and not self._faulted:
                self.fault_since = time.monotonic()
            self._faulted = bool(self.arm.fault)
            if self.runtime_state == PLAYING:
                if self.arm.fault:
                    self._end_program(f"protective stop: {self.arm.fault}")
                elif self.watchdog_hz > 0 and time.monotonic() - self.last_kick > 1.0 / self.watchdog_hz:
                    self._end_program("watchdog: no kick within its period; program stopped")
                    self._brake = 4.0
                else:
                    self._script_step()
            if self.runtime_state != PLAYING and self._brake > 0 and self.arm.brake(self._brake):
                self._brake = 0.0

    def _end_program(self, why: str) -> None:
        if self.runtime_state == PLAYING:
            self.log.append(why)
        self.runtime_state = STOPPED
        self.servo = None
        self._running = None
        self._profile = None
        self.out_int[0] = 0

    def _script_step(self) -> None:
        cmd = self.in_int[CMD_REGISTER]
        d = self.in_double
        if self.servo is not None and cmd in (0, SERVOJ):
            target, lookahead, gain = self.servo
            self.arm.servo(target, lookahead, gain)
        if cmd == 0:
            self._running = None
            self.out_int[0] = 1
            return
        if cmd in REALTIME:
            self.out_int[0] = 1
            return
        if self._running is None:  # a new command: run it once
            self._running = cmd
            self.servo = None
            if cmd == MOVEJ:
                self._profile = move_j_profile(self.arm.q, np.array(d[0:6]), d[6], d[7], DT)
                self._profile_i = 0
            elif cmd in (STOPJ, SERVOSTOP):
                self._brake = d[0] or 4.0
            elif cmd == SET_WATCHDOG:  # 0 turns it off
                self.watchdog_hz, self.last_kick = d[0], time.monotonic()
            elif cmd == STOP_SCRIPT:
                self._end_program("stopScript: program ended")
                return
        if self.out_int[0] == 2:
            return
        if self._running == MOVEJ and self._profile is not None:
            if self._profile_i < len(self._profile):
                self.arm.jump_to(self._profile[self._profile_i])
                self._profile_i += 1
                return
        elif self._running in (STOPJ, SERVOSTOP) and not self.arm.brake(self._brake):
            return
        self.out_int[0] = 2

    # --- what RTDE reads ----------------------------------------------------------------------------

    def value(self, name: str) -> object:
        """A variable's current value, for an output package (lock held by the caller)."""
        arm = self.arm
        if name == "timestamp":
            return time.monotonic() - self.started
        if name in ("actual_q", "target_q"):
            return list(arm.q if name == "actual_q" else arm.target)
        if name in ("actual_qd", "target_qd"):
            return list(arm.qd)
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return list(forward_kinematics(arm.q.copy()))
        if name == "runtime_state":
            return self.runtime_state
        if name == "robot_mode":
            return ROBOT_MODE_RUNNING
        if name == "safety_mode":
            return SAFETY_PROTECTIVE_STOP if arm.fault else SAFETY_NORMAL
        if name == "safety_status_bits":
            return (1 << 2) if arm.fault else 1  # bit 0 normal mode, bit 2 protective stopped
        if name == "robot_status_bits":
            return 0b1 | (0b10 if self.runtime_state == PLAYING else 0)  # power on, program running
        if name == "joint_mode":
            return [JOINT_MODE_RUNNING] * 6
        if name in ("speed_scaling", "target_speed_fraction"):
            return 1.0
        if name == "actual_digital_output_bits":
            return self.digital_out
        if name == "actual_digital_input_bits":
            return self.digital_in
        if name.startswith("output_int_register_"):
            return self.out_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self.out_double[int(name.rsplit("_", 1)[1])]
        return None  # zeros of the variable's type
