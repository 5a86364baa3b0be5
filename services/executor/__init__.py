"""The executor's public interface: what code outside the service may use of it (the benchmarks drive
its servo loop on its backends the executor's own way). Everything else in this folder is the service's
own and may change with it."""

from services.executor.backends import RobotUnavailable, SimBackend, UrRtdeBackend
from services.executor.servo import MotionResult, ServoLoop

__all__ = ["MotionResult", "RobotUnavailable", "ServoLoop", "SimBackend", "UrRtdeBackend"]
