"""`cadence view`: a running cell in Foxglove, through the Foxglove SDK's WebSocket server.

Every topic of the graph is a channel: its key (with a leading ``/``), JSON messages, and its message
type's JSON schema (msgspec's), so every field can be plotted. The topics that are not families are
advertised at start, so a client sees the whole graph before any traffic; a family's members
(``health/<service>``) appear with their first message. ``robot/state`` is also given in Foxglove's own
schemas: ``/robot/joint_states`` (foxglove.JointStates), ``/tf`` (foxglove.FrameTransforms, the UR16e's
links from its DH table) and ``/robot/model`` (foxglove.SceneUpdate, a line per link locked to its frame),
so the 3D panel shows the arm move. Log time is the message's data
time. ``deploy/foxglove/cadence.layout.json`` is a layout for it: the window mean RR with the thresholds
of Alg. 1 (carried by each selection), k, the joints, the events and the services' health.
"""

from __future__ import annotations

import math
import time
from typing import Any

import foxglove
import msgspec
import numpy as np

from common.robot.ur16e import DH_A, DH_ALPHA, DH_D, JOINT_NAMES
from schemas import RobotState
from schemas.topology import TOPICS, decode_any, key, topic_of

JOINT_STATES = "/robot/joint_states"
TF = "/tf"
SCENE = "/robot/model"  # the arm's links as lines, locked to their frames
SCENE_PERIOD_S = 1.0
# the UR16e's frames, base to flange, as ur_description names them
FRAMES = ("base_link", "shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link",
          "wrist_3_link")  # fmt: skip


def dh_transforms(q: np.ndarray) -> list[np.ndarray]:
    """Each link's 4×4 transform from the one before it (standard DH), for joint angles q."""
    out = []
    for theta, d, a, alpha in zip(q, DH_D, DH_A, DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        out.append(np.array([[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st], [0, sa, ca, d],
                             [0, 0, 0, 1]]))  # fmt: skip
    return out


def quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method: stable near every angle)."""
    tr = float(np.trace(r))
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
    v = [0.0, 0.0, 0.0]
    v[i] = 0.25 * s
    v[j] = (r[j, i] + r[i, j]) / s
    v[k] = (r[k, i] + r[i, k]) / s
    return (v[0], v[1], v[2], (r[k, j] - r[j, k]) / s)


# Foxglove's own schemas, JSON-encoded (the app knows them by name): the fields this bridge fills
_XYZ = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_STAMP = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_JOINT = {"type": "object", "properties": {"name": {"type": "string"}, "position": {"type": "number"},
                                           "velocity": {"type": "number"}}}  # fmt: skip
JOINT_STATES_SCHEMA = {
    "type": "object",
    "properties": {"timestamp": _STAMP, "joints": {"type": "array", "items": _JOINT}},
}
_TRANSFORM = {
    "type": "object",
    "properties": {
        "timestamp": _STAMP,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _XYZ,
        "rotation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}},
    },
}
FRAME_TRANSFORMS_SCHEMA = {
    "type": "object",
    "properties": {"transforms": {"type": "array", "items": _TRANSFORM}},
}


def _stamp(t_ns: int) -> dict[str, int]:
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def joint_states(state: RobotState) -> dict[str, Any]:
    each = zip(JOINT_NAMES, state.q, state.qd, strict=True)
    joints = [{"name": n, "position": p, "velocity": v} for n, p, v in each]
    return {"timestamp": _stamp(state.t_ns), "joints": joints}


def frame_transforms(q: list[float], t_ns: int) -> dict[str, Any]:
    """foxglove.FrameTransforms of the UR16e's links for joint angles q."""
    out = []
    for parent, child, t in zip(FRAMES[:-1], FRAMES[1:], dh_transforms(np.asarray(q)), strict=True):
        x, y, z, w = quaternion(t[:3, :3])
        out.append({
            "timestamp": _stamp(t_ns), "parent_frame_id": parent, "child_frame_id": child,
            "translation": {"x": float(t[0, 3]), "y": float(t[1, 3]), "z": float(t[2, 3])},
            "rotation": {"x": float(x), "y": float(y), "z": float(z), "w": float(w)},
        })  # fmt: skip
    return {"transforms": out}


def link_points() -> list[tuple[float, float, float]]:
    """Where each link's parent frame origin lies in the link's own frame. With standard DH this does not
    depend on the joint angle (the inverse of Rz(θ)·Tz(d)·Tx(a)·Rx(α) maps the origin to Rx(−α)·(−a, 0, −d)),
    so the arm's segments are drawn once, locked to their frames, and move with /tf."""
    out = []
    for d, a, alpha in zip(DH_D, DH_A, DH_ALPHA, strict=True):
        ca, sa = math.cos(-alpha), math.sin(-alpha)
        out.append((float(-a), float(sa * d), float(-d * ca)))
    return out


def arm_scene(t_ns: int) -> dict[str, Any]:
    """foxglove.SceneUpdate: one line per link, from its parent's origin to its own, in its own frame."""
    entities = []
    for i, (child, p) in enumerate(zip(FRAMES[1:], link_points(), strict=True)):
        entities.append({
            "timestamp": _stamp(t_ns), "frame_id": child, "id": f"ur16e_link_{i + 1}", "frame_locked": True,
            "lifetime": {"sec": 0, "nsec": 0},
            "lines": [{"type": 0, "thickness": 0.07, "scale_invariant": False,
                       "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                       "points": [{"x": 0.0, "y": 0.0, "z": 0.0}, {"x": p[0], "y": p[1], "z": p[2]}],
                       "color": {"r": 0.2, "g": 0.45, "b": 0.8, "a": 1.0}}],
        })  # fmt: skip
    return {"deletions": [], "entities": entities}


SCENE_SCHEMA = {
    "type": "object",
    "properties": {"entities": {"type": "array"}, "deletions": {"type": "array"}},
}


def _json_channel(topic: str, name: str, schema: Any, context: foxglove.Context) -> foxglove.Channel:
    return foxglove.Channel(
        topic,
        schema=foxglove.Schema(name=name, encoding="jsonschema", data=msgspec.json.encode(schema)),
        message_encoding="json",
        context=context,
    )


class Bridge:
    """The cell's keys as Foxglove channels of one SDK context (a server, or an MCAP writer, sinks it)."""

    def __init__(self, cell: str, context: foxglove.Context | None = None) -> None:
        self.cell = cell
        self.context = context or foxglove.Context()
        self.channels: dict[str, foxglove.Channel] = {}
        self.joints = _json_channel(JOINT_STATES, "foxglove.JointStates", JOINT_STATES_SCHEMA, self.context)
        self.tf = _json_channel(TF, "foxglove.FrameTransforms", FRAME_TRANSFORMS_SCHEMA, self.context)
        self.scene = _json_channel(SCENE, "foxglove.SceneUpdate", SCENE_SCHEMA, self.context)
        self._scene_at = 0.0
        self.undecodable = 0
        for t in TOPICS:
            if t.pattern == "topic" and "*" not in t.suffix:
                self._channel(key(cell, t.suffix))

    def _channel(self, key: str) -> foxglove.Channel | None:
        if key in self.channels:
            return self.channels[key]
        topic = topic_of(key)
        if topic is None:
            return None
        name = str(topic.message.__struct_config__.tag)
        ch = _json_channel("/" + key, name, msgspec.json.schema(topic.message), self.context)
        self.channels[key] = ch
        return ch

    def on(self, key: str, payload: bytes) -> None:
        try:
            msg: Any = decode_any(payload)
        except msgspec.DecodeError:
            self.undecodable += 1
            return
        ch = self._channel(key)
        if ch is not None:
            ch.log(msgspec.json.encode(msg), log_time=msg.t_ns)
        if isinstance(msg, RobotState):
            self.joints.log(msgspec.json.encode(joint_states(msg)), log_time=msg.t_ns)
            self.tf.log(msgspec.json.encode(frame_transforms(msg.q, msg.t_ns)), log_time=msg.t_ns)
            if time.monotonic() - self._scene_at >= SCENE_PERIOD_S:  # for a client that joins late
                self._scene_at = time.monotonic()
                self.scene.log(msgspec.json.encode(arm_scene(msg.t_ns)), log_time=msg.t_ns)
