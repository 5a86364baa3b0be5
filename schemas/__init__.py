"""The wire contract: msgspec Structs, one module per topic family, and the topology. Nothing else."""

from schemas.base import Message
from schemas.clock import CellClock
from schemas.decision import Selection
from schemas.ecg import AccChunk, EcgChunk, RrIntervals
from schemas.health import ServiceStatus
from schemas.hrv import Beats, HrvWindow
from schemas.operator import Calibration, OperatorError, OperatorSignal, Separation
from schemas.pareto import ParetoSet, ParetoSolution, ParetoSolutionReply, PlanProgress
from schemas.robot import CycleReport, RobotEvent, RobotState

__all__ = [
    "AccChunk",
    "Beats",
    "Calibration",
    "CellClock",
    "CycleReport",
    "EcgChunk",
    "HrvWindow",
    "Message",
    "OperatorError",
    "OperatorSignal",
    "ParetoSet",
    "ParetoSolution",
    "ParetoSolutionReply",
    "PlanProgress",
    "RobotEvent",
    "RobotState",
    "RrIntervals",
    "Selection",
    "Separation",
    "ServiceStatus",
]
