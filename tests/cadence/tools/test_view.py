"""`cadence view`: the cell in Foxglove. A WebSocket client speaking Foxglove's protocol (the SDK's
``foxglove.sdk.v1``) sees every topic of the graph advertised with its JSON schema, subscribes, and
decodes what the cell publishes: a window as JSON, the arm's state as foxglove.JointStates and its links
as foxglove.FrameTransforms. The shipped layout names only channels the bridge gives."""

from __future__ import annotations

import asyncio
import json
import re
import signal
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import websockets

from cadence.tools.view import FRAMES, JOINT_STATES, SCENE, TF, arm_scene, dh_transforms, link_points
from common.robot.ur16e import forward_kinematics
from common.runtime.bus import Bus, BusConfig
from common.runtime.resources import FOXGLOVE_LAYOUT
from schemas import HrvWindow, RobotState
from schemas.topology import TOPICS
from tests.support.cell import CELL, free_port, put

PROTOCOL = "foxglove.sdk.v1"


async def advertised(ws, wanted: set[str]) -> dict[str, dict]:
    """Channels by topic, read from the server's advertise messages until ``wanted`` are all there."""
    channels: dict[str, dict] = {}
    async with asyncio.timeout(30):
        while not wanted <= channels.keys():
            msg = json.loads(await ws.recv())
            if msg["op"] == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
    return channels


async def next_message(ws, sub_ids: dict[int, str]) -> tuple[str, bytes]:
    async with asyncio.timeout(30):
        while True:
            data = await ws.recv()
            if (
                isinstance(data, bytes) and data[0] == 0x01
            ):  # message data: op, subscription, log time, payload
                sub, _ = struct.unpack_from("<IQ", data, 1)
                return sub_ids[sub], data[13:]


@pytest.mark.asyncio
async def test_a_foxglove_client_sees_the_graph_and_decodes_the_cell(endpoint: str) -> None:
    port = free_port()
    q = [0.3, -1.2, 1.5, -1.8, -1.57, 0.4]
    async with await Bus.open(BusConfig(listen=[endpoint]), CELL) as bus:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cadence", "view", "--connect", endpoint, "--port", str(port),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        )  # fmt: skip
        try:
            await bus.until_subscribed(bus.key("robot/state"), timeout=60)  # the bridge reads the cell
            async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[PROTOCOL]) as ws:
                info = json.loads(await ws.recv())
                assert info["op"] == "serverInfo"
                assert info["name"] == f"cadence {CELL}"
                graph = {
                    f"/cadence/{CELL}/{t.suffix}"
                    for t in TOPICS
                    if t.pattern == "topic" and "*" not in t.suffix
                }
                channels = await advertised(ws, graph | {"/robot/joint_states", "/tf", "/robot/model"})
                window_ch = channels[f"/cadence/{CELL}/hrv/window"]
                assert (window_ch["encoding"], window_ch["schemaName"]) == ("json", "hrv.window.v1")
                assert "mean_rr_s" in json.loads(window_ch["schema"])["$defs"]["HrvWindow"]["properties"]
                print("channels:", ", ".join(sorted(channels)))
                wanted = [f"/cadence/{CELL}/hrv/window", JOINT_STATES, TF, SCENE]
                sub_ids = {i: topic for i, topic in enumerate(wanted, start=1)}
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": i, "channelId": channels[t]["id"]} for i, t in sub_ids.items()]}))  # fmt: skip
                w = HrvWindow(t_ns=30 * 10**9, seq=0, start_ns=10**9, end_ns=30 * 10**9, mean_rr_s=0.81,
                              n_beats=37, excluded_fraction=0.0, quality="good")  # fmt: skip
                state = RobotState(t_ns=31 * 10**9, seq=0, q=q, qd=[0.1] * 6, tcp=[0.0] * 6)

                async def cell() -> None:
                    """The server takes a subscription on its own time and says nothing when it has: the
                    cell goes on publishing, as a running one does, until the client has them all."""
                    while True:
                        put(bus, bus.key("hrv/window"), w, block=True)
                        put(bus, bus.key("robot/state"), state)
                        await asyncio.sleep(0.2)

                publishing = asyncio.ensure_future(cell())
                got: dict[str, dict] = {}
                try:
                    while len(got) < len(wanted):
                        topic, payload = await next_message(ws, sub_ids)
                        got[topic] = json.loads(payload)
                finally:
                    publishing.cancel()
        finally:
            proc.send_signal(signal.SIGINT)
            await asyncio.wait_for(proc.wait(), 30)
    assert proc.returncode == 0
    assert got[f"/cadence/{CELL}/hrv/window"]["mean_rr_s"] == 0.81
    joints = got["/robot/joint_states"]["joints"]
    assert [j["position"] for j in joints] == pytest.approx(q)
    assert joints[0]["name"] == "base"
    assert [e["frame_id"] for e in got[SCENE]["entities"]] == list(FRAMES[1:])  # the arm's links
    tf = got["/tf"]["transforms"]
    assert [t["child_frame_id"] for t in tf] == list(FRAMES[1:])
    # the links' chain ends where the arm's forward kinematics puts the flange
    end = np.eye(4)
    for t in dh_transforms(np.asarray(q)):
        end = end @ t
    assert end[:3, 3] == pytest.approx(forward_kinematics(np.asarray(q))[:3])
    assert [tf[0]["translation"][k] for k in "xyz"] == pytest.approx([0.0, 0.0, 0.1807])


def test_the_arm_model_s_links_join_their_frames_at_every_pose() -> None:
    """Each link's line, drawn once in its own frame, ends at its parent's origin whatever the joints."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        for t, p in zip(dh_transforms(rng.uniform(-np.pi, np.pi, 6)), link_points(), strict=True):
            assert (t @ np.array([*p, 1.0]))[:3] == pytest.approx(np.zeros(3), abs=1e-12)
    scene = arm_scene(10**9)
    assert [e["frame_id"] for e in scene["entities"]] == list(FRAMES[1:])


def test_the_shipped_layout_names_only_channels_and_fields_the_bridge_gives() -> None:
    import msgspec

    layout = json.loads(Path(FOXGLOVE_LAYOUT).read_text())
    types = {f"/cadence/{CELL}/{t.suffix}": t.message for t in TOPICS if t.pattern == "topic"}
    topics = set(types) | {JOINT_STATES, TF, SCENE}
    named, plotted = set(), set()
    for config in layout["configById"].values():
        for path in [p["value"] for p in config.get("paths", [])] + [config.get("topicPath", "")]:
            if path:
                named.add(re.match(r"[^.]+", path).group(0))
        plotted |= {p["value"] for p in config.get("paths", [])}
        named |= set(config.get("topics", {}))
    assert named, "the layout names no topic"
    for topic in named:
        assert topic in topics or re.fullmatch(rf"/cadence/{CELL}/health/\w+", topic), topic
    for path in plotted:  # a plotted field of a Cadence message is one of its fields
        topic, _, field = path.partition(".")
        if topic in types:
            assert field in {f.name for f in msgspec.structs.fields(types[topic])}, path
    # RR is plotted with the thresholds k is decided against
    selection = f"/cadence/{CELL}/decision/selection"
    thresholds = {f"{selection}.rr_rest_s", f"{selection}.rr_stress_s", f"{selection}.rr_stress_max_s"}
    assert thresholds | {f"/cadence/{CELL}/hrv/window.mean_rr_s"} <= plotted
    assert f"/cadence/{CELL}/hrv/window.movement_mg" in plotted  # and movement beside them
