"""The executor's settings (``[executor]`` in a deployment config; DESIGN §8, §9): apart from the service's
``__main__`` so that the executor's modules read them without importing the service that runs them."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from common.robot.stopping import UR16E_SOURCE, UR16E_STOPS, RobotStops, StopRow
from common.runtime.errors import ConfigError
from common.runtime.resources import EXAMPLE_TASK
from common.safety.geometry import NO_TOOL, Arm, Detects, Pose, Sensor, Tool, intrusion_iso13855
from common.safety.separation import Ssm
from common.safety.watch import Rules
from schemas.decision import MAX_N


def _range(lo: float, hi: float) -> msgspec.Meta:
    return msgspec.Meta(ge=lo, le=hi)


Metres = Annotated[float, _range(-100.0, 100.0)]
PoseRow = tuple[Metres, Metres, Metres, Annotated[float, _range(-360.0, 360.0)]]
Near = Annotated[float, _range(-2.0, 2.0)]
Sphere = tuple[Near, Near, Near, Annotated[float, _range(0.0, 2.0)]]
# a gripper and a small part, 0.27 m past the flange at most: what the example task's EPick and box need
DEFAULT_TOOL = (0.0, 0.0, 0.15, 0.12)
SourceName = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]


class SourceSettings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """One separation source of the cell (``separation_sources``; common/safety/geometry.py): where it
    stands, what it detects (its C by ISO 13855), and what its plain distances mean."""

    name: SourceName
    pose: PoseRow = (0.0, 0.0, 0.0, 0.0)  # in the cell frame: x, y, z (m), yaw (°)
    detects: Detects = "legs"  # hand, arm, body, legs, beam (a single one): ISO 13855's C follows
    resolution_mm: Annotated[float, _range(1.0, 500.0)] | None = None
    # legs: the scan plane above the floor (H); 0: the pose's z, with which it must agree when both are given
    height_m: Annotated[float, _range(0.0, 3.0)] = 0.0
    intrusion_m: Annotated[float, _range(0.0, 3.0)] | None = None  # a C of its own, never below ISO 13855's
    to_robot: bool = False  # its plain distances are measured to the arm already (else: from the sensor)
    pitch_deg: Annotated[float, _range(-180.0, 180.0)] = 0.0  # a sensor not level: 90 looks straight down
    roll_deg: Annotated[float, _range(-180.0, 180.0)] = 0.0

    @classmethod
    def parse(cls, text: str) -> SourceSettings:
        """``NAME:POSE:KIND[,OPTION=VALUE…]`` as `cadence install --scanner` takes it (the name may hold
        colons). POSE in the cell frame: ``X,Y,YAW``, ``X,Y,Z,YAW`` or ``X,Y,Z,ROLL,PITCH,YAW`` (m, degrees);
        KIND one of hand, arm, body, legs, beam, a scanner's plane height after ``@`` (``legs@0.3``); the
        options ``resolution`` (mm), ``height`` (m), ``c`` (m: a C of its own). Checked as the executor
        checks it at start (``sensor``): ValueError says what is wrong, in one line."""
        name, pose, kind = text.rsplit(":", 2) if text.count(":") >= 2 else (text, "", "")
        if not (name and pose and kind):
            raise ValueError(f"expected NAME:X,Y,YAW:KIND (e.g. scanner:front:1.2,0,180:legs@0.3, or "
                             f"cam:top:0,0,3,0,90,0:hand,resolution=14), got {text!r}")  # fmt: skip
        kind, *options = kind.split(",")
        detects, _, height = kind.partition("@")
        fields: dict[str, object] = {"name": name, "detects": detects, "height_m": float(height or 0)}
        try:
            v = [float(x) for x in pose.split(",")]
            if len(v) not in (3, 4, 6):
                raise ValueError(f"a pose is X,Y,YAW, X,Y,Z,YAW or X,Y,Z,ROLL,PITCH,YAW, got {pose!r}")
            x, y, z = v[0], v[1], v[2] if len(v) > 3 else 0.0
            fields |= {"pose": [x, y, z, v[-1]]}
            if len(v) == 6:
                fields |= {"roll_deg": v[3], "pitch_deg": v[4]}
            for option in options:
                key, _, value = option.partition("=")
                if key not in OPTIONS or not value:
                    raise ValueError(
                        f"unknown option {option!r} (expected {', '.join(f'{k}=' for k in OPTIONS)})"
                    )
                fields[OPTIONS[key]] = float(value)
            src = msgspec.convert(fields, cls)
            src.sensor()
            return src
        except (ValueError, msgspec.ValidationError, ConfigError) as exc:
            raise ValueError(f"{text!r}: {exc}") from None

    def sensor(self) -> Sensor:
        """The source as separation monitoring sees it, with its C by ISO 13855; ``ConfigError`` naming it
        for a C below the standard's, a plane height that disagrees with the pose's z, or what ISO 13855
        cannot say (a hand sensor with no resolution of 40 mm or finer, a leg scanner over 1 m)."""
        where = f"[executor] separation_sources '{self.name}'"
        x, y, z, yaw = self.pose
        height = self.height_m or z
        if self.detects == "legs" and self.height_m and z and abs(self.height_m - z) > 1e-3:
            raise ConfigError(f"{where}: height_m = {self.height_m:g} m, but its pose stands at z = {z:g} m: "
                              "a leg scanner's plane is at its own height (give one of them)")  # fmt: skip
        try:
            iso = intrusion_iso13855(self.detects, self.resolution_mm, height)
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
        c = iso if self.intrusion_m is None else self.intrusion_m
        if c < iso - 1e-9:
            raise ConfigError(
                f"{where}: intrusion_m = {c:g} m is below ISO 13855's C = {iso:.3f} m for a sensor that "
                f"detects {self.detects}" + (f" at {height:g} m" if self.detects == "legs" else "")
            )
        return Sensor(self.name, Pose(x, y, z, yaw, self.pitch_deg, self.roll_deg), c, self.to_robot)


OPTIONS = {"resolution": "resolution_mm", "height": "height_m", "c": "intrusion_m"}  # --scanner's options


class Settings(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    """The executor's ``[executor]`` settings, checked whole at start: a wrong one is one line, exit 2."""

    task: str = str(EXAMPLE_TASK)
    backend: Literal["sim", "ur_rtde"] = "sim"
    host: str = "127.0.0.1"  # ur_rtde: the controller
    lookahead_s: Annotated[float, _range(0.03, 0.2)] = 0.1  # servoJ (UR's range)
    gain: Annotated[float, _range(100.0, 2000.0)] = 300.0  # servoJ (UR's range)
    gripper_output: Annotated[int, _range(0, 7)] = 0  # standard digital output driving the gripper
    watchdog_hz: Annotated[float, _range(1.0, 500.0)] = 10.0  # ur_rtde: the arm stops below this rate
    servo_core: Annotated[int, _range(0, 4095)] | None = None  # default: the last free core
    lock_dir: str | None = None  # where executors claim cores (default /run/cadence)
    fifo_priority: Annotated[int, _range(0, 99)] = 80  # 0: no SCHED_FIFO
    lock_memory: bool = True
    # the servo loop without SCHED_FIFO, locked memory or a core of its own: "required" refuses to start,
    # in one line saying which and how to grant it; "optional" runs on and says so (the log, `cadence top`).
    # Default: required with a real robot (ur_rtde), optional on the sim
    realtime: Literal["required", "optional"] | None = None
    # where the 500 Hz loop, the path it plays and the backend run: a process of their own, which no thread
    # of the executor can starve through the GIL (services/executor/servo_process.py); or a thread of the
    # executor (a host where a process cannot be started: no memfd)
    servo: Literal["process", "thread"] = "process"
    spin_us: Annotated[int, _range(0, 1900)] = 400
    overrun_limit: Annotated[int, _range(1, 1000)] = 5  # this many overruns in a row stop the robot
    stop_deceleration: Annotated[float, _range(0.5, 40.0)] = 4.0  # rad/s², SIGTERM and overrun stops
    settle_s: Annotated[float, _range(0.0, 10.0)] = 0.5  # after the last sample, wait this long at most
    start_policy: Literal["move", "refuse"] = "move"  # the arm is not at the path's start
    start_speed: Annotated[float, _range(0.01, 1.0)] = 0.3  # rad/s, the slow move there
    start_acceleration: Annotated[float, _range(0.01, 2.0)] = 0.6  # rad/s²
    start_tolerance_rad: Annotated[float, _range(1e-5, 0.05)] = 2e-3
    # With the decision maker unreachable at start: "wait" for it, go on at the "last" selection applied
    # (if younger than last_selection_max_age_s), or start at "initial" initial_k. Default: "wait" for
    # ur_rtde, "last" for sim.
    start_selection: Literal["wait", "last", "initial"] | None = None
    last_selection_max_age_s: Annotated[float, _range(0.0, 86400.0)] = 300.0
    initial_k: Annotated[int, _range(1, MAX_N)] = 8  # start_selection = "initial" (Alg. 1's k0 for N = 15)
    # the decision maker's period (a window): a selection stamped more than this before the one in force
    # is refused, however its seq is numbered
    selection_period_s: Annotated[float, _range(0.1, 3600.0)] = 30.0
    # A stop is latched until `cadence robot resume`; "auto" (sim only) resumes after auto_resume_s,
    # doubling, at most auto_resume_per_hour times an hour.
    resume_policy: Literal["manual", "auto"] = "manual"
    auto_resume_s: Annotated[float, _range(0.1, 600.0)] = 2.0
    auto_resume_per_hour: Annotated[int, _range(1, 10_000)] = 10
    state_rate_hz: Annotated[float, _range(1.0, 500.0)] = 50.0  # robot/state, wall clock
    query_timeout_s: Annotated[float, _range(0.1, 60.0)] = 2.0
    wait_for_signals: bool = True  # false: `wait_for` steps pass at once (no operator on the bus)
    # a signal stamped longer ago than this (data s) is about another moment: refused, as one from the future
    signal_max_age_s: Annotated[float, _range(1.0, 3600.0)] = 60.0
    cycles: Annotated[int, _range(0, 10**9)] = 0  # stop after this many cycles; 0: run until stopped
    sim_start_deg: list[Annotated[float, _range(-360.0, 360.0)]] | None = None  # sim: pose at start
    # A new selection during a path re-times the rest of it with the new solution (continuous to the
    # jerk, checked), from switch_lead_s ahead; false: it waits for the next path start, as the paper does.
    switch_within_path: bool = True
    switch_lead_s: Annotated[float, _range(0.01, 1.0)] = 0.1
    # Speed and separation monitoring (ISO/TS 15066; common/safety/separation.py): the time scale follows the
    # nearest fresh distance of every source on operator/separation; none fresh (younger than
    # separation_max_age_s), or none from a declared source, holds the arm on its path. Off: the robot
    # always runs at the planned speed.
    separation: bool = False
    # the cell's sources, each of which must be heard (one silent holds the arm): a table each (pose,
    # detects, ...: SourceSettings), or a bare name, read as a scanner at the robot's base that sees legs
    # at the floor (the largest C) and gives ranges from itself. Monitoring on with none is refused.
    separation_sources: list[SourceName | SourceSettings] = []
    separation_max_rate_hz: Annotated[float, _range(1.0, 100_000.0)] = 1000.0  # per source; past it: a hold
    # the separation guard beside a servo process (services/executor/guard_process.py): readings judged in a
    # process of their own, whatever the executor's loop must decode; off, the executor's looks alone
    separation_guard: bool = True
    # a reading from a source not declared above: "use" it (the nearest still wins: a simulated cell, a
    # sensor being tried), or "refuse" it, counted (an installed cell: `cadence install` writes it, so that
    # only the declared scanners, each on its own account, say where people are)
    separation_undeclared: Literal["use", "refuse"] = "use"
    # where the robot's base stands in the cell frame (x, y, z m, yaw °), and its tool and payload as
    # spheres in the flange frame (x, y, z, r m): the distance and the top speed are to and of these too
    robot_base: PoseRow = (0.0, 0.0, 0.0, 0.0)
    tool: list[Sphere] = msgspec.field(default_factory=lambda: [DEFAULT_TOOL])
    separation_max_age_s: Annotated[float, _range(0.01, 10.0)] = 0.3  # the oldest reading used (T_r)
    # T_r, the reaction time, is the sum of sensor_latency_s, separation_max_age_s, the cell's
    # clock_skew_s, adoption_budget_s and, on ur_rtde, lookahead_s (docs/robot.md, "Reacting within a path")
    sensor_latency_s: Annotated[float, _range(0.0, 2.0)] = 0.1  # what the sensor's age_s leaves out
    # from a reading's arrival to the controller step that plays the scale it led to (look, planning,
    # mailbox, servo), measured on the loop's clock for every look: past it the arm holds until it is met
    adoption_budget_s: Annotated[float, _range(0.03, 1.0)] = 0.1
    human_speed_m_s: Annotated[float, _range(0.0, 5.0)] = 1.6  # v_h (ISO 13855)
    stop_time_s: Annotated[float, _range(0.0, 5.0)] = 0.0  # T_s at least this (each path's own is found)
    # the robot's own stops, which S_p budgets beside the executor's ramp (common/robot/stopping.py): the
    # figures measured on the installed robot (ISO 10218-1 Annex B), or its safety configuration's Stopping
    # Time limit, a row each; none: the backend's own (ur_rtde: a stated conservative 0.75 s for every
    # stop; sim: its brake alone). The brake (stop_deceleration) and the watchdog are budgeted always.
    robot_stops: list[StopRow] = []
    robot_stops_source: str = "measured on the installed robot"
    uncertainty_m: Annotated[float, _range(0.0, 2.0)] = 0.1  # Z_d + Z_r
    scale_period_s: Annotated[float, _range(0.005, 1.0)] = 0.02  # how often the scale is reconsidered

    @property
    def state_period_s(self) -> float:
        return 1.0 / self.state_rate_hz

    def reaction_parts(self, clock_skew_s: float) -> dict[str, float]:
        """T_r's parts, in seconds, by name: what lies between a person's move and the arm's answer."""
        return {
            "sensor latency": self.sensor_latency_s,
            "oldest reading used": self.separation_max_age_s,
            "clock skew": clock_skew_s,
            "executor's adoption": self.adoption_budget_s,  # the ramp's lead is inside it
            "servoJ lookahead": self.lookahead_s if self.backend == "ur_rtde" else 0.0,
        }

    def rules(self, clock_skew_s: float) -> Rules:
        """How readings are judged and what S_p counts, for the executor's looks and its guard alike."""
        parts = self.reaction_parts(clock_skew_s)
        ssm = Ssm(self.human_speed_m_s, sum(parts.values()), self.stop_time_s, 0.0, self.uncertainty_m,
                  self.separation_max_age_s)  # fmt: skip
        return Rules(self.arm(), self.sensors(), ssm, self.separation_max_age_s, clock_skew_s,
                     self.separation_max_rate_hz, self.separation_undeclared == "refuse",
                     self.adoption_budget_s)  # fmt: skip

    def arm(self) -> Arm:
        """The robot as separation monitoring sees it: its base in the cell, its tool, its own stops."""
        x, y, z, yaw = self.robot_base
        tool = Tool.of([list(t) for t in self.tool]) if self.tool else NO_TOOL
        return Arm(Pose(x, y, z, yaw), tool, self.stops())

    def stops(self) -> RobotStops:
        """The robot's stops S_p budgets; ``ConfigError`` for a table that does not reach full speed."""
        if self.robot_stops:
            rows, source = tuple(self.robot_stops), self.robot_stops_source
        elif self.backend == "ur_rtde":
            rows, source = UR16E_STOPS, UR16E_SOURCE
        else:
            rows, source = (), "the simulated controller brakes, and has no stop of its own"
        try:
            return RobotStops(rows, source, self.stop_deceleration, 1.0 / self.watchdog_hz)
        except ValueError as exc:
            raise ConfigError(f"[executor] {exc}") from None

    def sensors(self) -> dict[str, Sensor]:
        """The declared sources by name, each with its C by ISO 13855; ``ConfigError`` in one line naming
        the source for a C below the standard's, a source named twice, or monitoring on with no source
        (nothing would tell a scanner that died from a cell with nobody in it)."""
        out: dict[str, Sensor] = {}
        for entry in self.separation_sources:
            src = SourceSettings(entry) if isinstance(entry, str) else entry
            if src.name in out:
                raise ConfigError(f"[executor] separation_sources '{src.name}' is declared twice")
            out[src.name] = src.sensor()
        if self.separation and not out:
            raise ConfigError(
                "[executor] separation = true needs separation_sources: declare each scanner or camera "
                '(e.g. separation_sources = ["scanner:front"], or a table with its pose and what it detects)'
            )
        return out
