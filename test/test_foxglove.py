"""Live view: the loop's topics on a Foxglove WebSocket, read back by a WebSocket client."""
import asyncio
import json
import os
import socket
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import free_port, run_main
import websockets
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from has_control.bag import msgdef
from has_control.common.errors import HasControlError
from has_control.nodes.controller_node import ControllerNode
from has_control.nodes.foxglove import LiveView
from has_control.nodes.runtime import tee
from has_control.nodes.plant_node import PlantNode
from has_control.wire.topics import CLOCK_LAYOUT, GAINS_LAYOUT, STATE_LAYOUT, STATE_NAMES

pytestmark = [pytest.mark.ros]

SUBPROTOCOL = "foxglove.sdk.v1"        # foxglove-sdk's name for foxglove.websocket.v1 (which it refuses)
RUN = {"/state", "/command", "/clock", "/controller/controller_state", "/controller/reference",
       "/controller/gains"}


async def _connect(port: int, deadline: float):
    while True:
        try:
            return await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                            max_size=None, open_timeout=5)
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)


async def _advertised(ws, topics: set, deadline: float) -> dict:
    """{topic: channel} once every one of ``topics`` is advertised."""
    channels = {}
    while not topics <= channels.keys():
        msg = await asyncio.wait_for(ws.recv(), max(deadline - time.monotonic(), 0.01))
        if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
            channels.update({c["topic"]: c for c in json.loads(msg)["channels"]})
    return channels


async def _subscribe(ws, channel: dict, sub_id: int = 1) -> None:
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": channel["id"]}]}))


def _message_data(frame: bytes) -> tuple[int, int, bytes]:
    """(subscription id, log time [ns], payload) of a binary message-data frame (opcode 0x01)."""
    op, sub, log_time = struct.unpack_from("<BIQ", frame)
    assert op == 0x01
    return sub, log_time, frame[13:]


async def _read_stack(port: int, n: int, timeout: float):
    deadline = time.monotonic() + timeout
    async with await _connect(port, deadline) as ws:
        channels = await _advertised(ws, RUN, deadline)
        await _subscribe(ws, channels["/state"], 7)
        frames = []
        while len(frames) < n:
            msg = await asyncio.wait_for(ws.recv(), max(deadline - time.monotonic(), 0.01))
            if isinstance(msg, bytes):
                frames.append(_message_data(msg))
        return channels, frames


def test_stack_serves_the_state_live_as_ros2msg_cdr(domain_id):
    """``has-control stack --foxglove PORT``: a client subscribes to /state and
    decodes JointState messages whose stamps advance by 0.3 ms."""
    port = free_port()
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    stack = subprocess.Popen([sys.executable, "-m", "has_control.cli", "stack", "--duration", "2", "--realtime",
                              "--foxglove", str(port)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        channels, frames = asyncio.run(_read_stack(port, 300, 60))
        out, err = stack.communicate(timeout=60)
    finally:
        stack.kill()
    assert stack.returncode == 0, err
    assert f"served live on ws://127.0.0.1:{port}" in out
    state = channels["/state"]
    assert (state["encoding"], state["schemaEncoding"], state["schemaName"]) == (
        "cdr", "ros2msg", "sensor_msgs/msg/JointState")
    assert state["schema"] == msgdef("sensor_msgs/msg/JointState")       # the text our bags hold
    assert state["schema"].startswith("std_msgs/Header header\nstring[] name\n")
    assert {channels[t]["schemaName"] for t in ("/controller/gains", "/controller/reference")} == {
        "std_msgs/msg/Float64MultiArray"}
    assert channels["/clock"]["schemaName"] == "rosgraph_msgs/msg/Clock"
    stamps = []
    for sub, log_time, payload in frames:
        msg = deserialize_message(payload, JointState)
        assert sub == 7 and list(msg.name) == STATE_NAMES and len(msg.position) == 3
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert log_time == stamp
        stamps.append(stamp)
    steps = np.diff(stamps)
    assert np.all(steps > 0) and np.all(steps % 300_000 == 0)
    assert np.mean(steps == 300_000) > 0.9          # a client that falls behind loses the oldest ones


async def _log_and_read(view: LiveView, messages: dict[str, bytes]) -> dict[str, tuple[int, bytes]]:
    takes = {topic: view.sink(topic) for topic in messages}        # the channels, as a node makes them
    async with await _connect(view.port, time.monotonic() + 10) as ws:
        channels = await _advertised(ws, set(messages), time.monotonic() + 10)
        ids = {}
        for i, topic in enumerate(messages):
            await _subscribe(ws, channels[topic], i + 1)
            ids[i + 1] = topic
        await asyncio.sleep(0.3)                  # the server takes the subscriptions
        for topic, data in messages.items():
            takes[topic](data)
        got = {}
        while len(got) < len(messages):
            sub, log_time, payload = _message_data(await asyncio.wait_for(ws.recv(), 10))
            got[ids[sub]] = (log_time, payload)
        return got


def test_log_time_is_simulation_time_for_every_type():
    state = STATE_LAYOUT.encode(range(9), 1_500_300_000)
    clock = CLOCK_LAYOUT.encode([], 2_000_000_000)
    gains = GAINS_LAYOUT.encode([0.25, 150.0, 158.0, 162.0])
    with LiveView(port=0) as view:
        got = asyncio.run(_log_and_read(view, {"/sim0/state": state, "/sim0/clock": clock,
                                               "/sim0/controller/gains": gains}))
        with pytest.raises(HasControlError, match="not a run topic"):
            view.sink("/chatter")
    assert got == {"/sim0/state": (1_500_300_000, state), "/sim0/clock": (2_000_000_000, clock),
                   "/sim0/controller/gains": (250_000_000, gains)}


def test_a_port_in_use_is_one_line_and_exit_2(capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = run_main(capsys, "stack", "--duration", "2", "--foxglove", port)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.startswith(f"has-control: error: --foxglove {port}: ") and r.stderr.count("\n") == 1
    assert "in use" in r.stderr


def test_foxglove_port_parameter_serves_the_nodes_topics(context):  # noqa: F811
    port = free_port()
    node = ControllerNode(context=context, parameter_overrides=[Parameter("foxglove_port", value=port)])
    try:
        assert node.live_view.port == port
        assert set(node.live_view.channels) == {"/command", "/controller/controller_state",
                                                "/controller/reference", "/controller/gains", "/diagnostics"}
        res = node.set_parameters([Parameter("foxglove_port", value=port + 1)])
        assert not res[0].successful and "read-only" in res[0].reason
    finally:
        node.destroy_node()
    plant = PlantNode(context=context)
    try:
        assert plant.live_view is None          # 0: off
    finally:
        plant.destroy_node()


@pytest.mark.parametrize("value", [-1, 65536])
def test_a_bad_foxglove_port_parameter_is_refused(context, value):  # noqa: F811
    with pytest.raises(ValueError, match=rf"parameter foxglove_port = {value}: expected a port 1..65535 or 0"):
        PlantNode(context=context, parameter_overrides=[Parameter("foxglove_port", value=value)])


def test_a_bad_foxglove_port_ends_the_node_with_one_line(domain_id):
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    r = subprocess.run([sys.executable, "-m", "has_control.cli", "controller", "--ros-args", "-p",
                        "foxglove_port:=-1"], env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().endswith("error: parameter foxglove_port = -1: expected a port 1..65535 or 0 (off)")
    assert r.stderr.count("\n") == 1


def test_tee_hands_each_message_to_every_tap():
    a, b = [], []
    one = a.append
    assert tee() is None and tee(None, one) is one
    tap = tee(lambda topic: a.append, None, lambda topic: b.append)("/state")
    tap(b"x")
    assert a == b == [b"x"]
