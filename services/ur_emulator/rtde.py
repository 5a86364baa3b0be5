"""The RTDE wire format (Universal Robots' Real-Time Data Exchange, protocol version 2), as the UR
controller emulator speaks it; shared/reference/ur-rtde-wire.md lists what the ur-rtde 1.6.5 client does.

Pure: framing, the type of every variable the client asks for, and packing by type. A frame is a
big-endian ``>HB`` header (total size including the header, then the type byte) and a payload.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence

V, v, M, U, O, I, S, P = (ord(c) for c in "VvMUOISP")  # noqa: E741
HEADER = struct.Struct(">HB")

# type name → struct format of one value
FORMATS = {
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
    "INT32": "i",
    "UINT32": "I",
    "UINT64": "Q",
    "UINT8": "B",
    "BOOL": "?",
}

_VECTOR6 = {
    "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q", "actual_qd",
    "actual_current", "actual_current_window", "joint_control_output", "actual_TCP_pose", "actual_TCP_speed",
    "actual_TCP_force", "target_TCP_pose", "target_TCP_speed", "joint_temperatures", "actual_joint_voltage",
    "ft_raw_wrench", "payload_inertia", "tcp_offset", "external_force_torque", "actual_current_as_torque",
    "target_current_window",
}  # fmt: skip
_VECTOR3 = {
    "actual_tool_accelerometer",
    "payload_cog",
    "elbow_position",
    "elbow_velocity",
    "tool_accelerometer",
}
_UINT32 = {"runtime_state", "robot_status_bits", "safety_status_bits", "speed_slider_mask", "analog_io_types"}
_UINT64 = {
    "actual_digital_input_bits",
    "actual_digital_output_bits",
    "output_bit_registers0_to_31",
    "output_bit_registers32_to_63",
    "input_bit_registers0_to_31",
    "input_bit_registers32_to_63",
}
_INT32 = {"robot_mode", "safety_mode", "tool_mode", "tool_output_voltage"}
_UINT8 = re.compile(
    r"(standard|configurable|tool)_digital_output(_mask)?|standard_analog_output_(mask|type)|tool_output_mode"
    r"|tool_digital_output[01]_mode"
)


def type_of(name: str) -> str:
    """The RTDE type of a variable, by name (the client decodes by its own table, so they must match)."""
    if name in _VECTOR6:
        return "VECTOR6D"
    if name in _VECTOR3:
        return "VECTOR3D"
    if name == "joint_mode":
        return "VECTOR6INT32"
    if name in _UINT64:
        return "UINT64"
    if name in _UINT32 or name.endswith("_bits"):
        return "UINT32"
    if name in _INT32 or re.fullmatch(r"(input|output)_int_register_\d+", name):
        return "INT32"
    if _UINT8.fullmatch(name):
        return "UINT8"
    if re.fullmatch(r"(input|output)_bit_register_\d+", name):
        return "BOOL"
    return "DOUBLE"


def frame(kind: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def recipe_struct(types: Sequence[str]) -> struct.Struct:
    return struct.Struct(">" + "".join(FORMATS[t] for t in types))


def flatten(values: Sequence[object]) -> list[object]:
    out: list[object] = []
    for x in values:
        if isinstance(x, list | tuple):
            out.extend(x)
        else:
            out.append(x)
    return out


def regroup(types: Sequence[str], flat: Sequence[object]) -> list[object]:
    """Unpacked fields back into one value per variable (vectors as lists)."""
    out: list[object] = []
    i = 0
    for t in types:
        n = int(FORMATS[t][0]) if FORMATS[t][0].isdigit() else 1
        out.append(list(flat[i : i + n]) if n > 1 else flat[i])
        i += n
    return out
