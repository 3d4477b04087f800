"""The live view off the loop: a ring the loop copies into, a viewer process,
the URL before the run, --foxglove-wait."""
import asyncio
import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import free_port
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from has_control.nodes.live_process import SLOTS, LiveViewProcess
from has_control.wire.topics import STATE_LAYOUT
from test_foxglove import _advertised, _connect, _message_data, _subscribe

pytestmark = [pytest.mark.ros]


def test_the_writer_never_waits_for_the_viewer_which_loses_the_oldest():
    """The loop's side writes three rings' worth while the viewer process is stopped
    (SIGSTOP): nothing waits; resumed, the viewer skips what was overwritten and
    delivers the newest, in order."""
    last = 3 * SLOTS
    with LiveViewProcess(port=0) as view:
        write = view.sink("/state")

        async def read():
            deadline = time.monotonic() + 60
            async with await _connect(view.port, deadline) as ws:
                channels = await _advertised(ws, {"/state"}, deadline)
                await _subscribe(ws, channels["/state"], 3)
                await asyncio.sleep(0.5)
                os.kill(view._proc.pid, signal.SIGSTOP)
                try:
                    for i in range(last + 1):
                        write(STATE_LAYOUT.encode(range(9), i * 300_000))
                finally:
                    os.kill(view._proc.pid, signal.SIGCONT)
                stamps = []
                while not stamps or stamps[-1] != last * 300_000:
                    msg = await asyncio.wait_for(ws.recv(), max(deadline - time.monotonic(), 0.01))
                    if isinstance(msg, bytes):
                        sub, log_time, payload = _message_data(msg)
                        assert sub == 3
                        stamps.append(log_time)
                return stamps, payload
        stamps, payload = asyncio.run(read())
    assert len(stamps) <= SLOTS and all(b > a for a, b in zip(stamps, stamps[1:]))   # the oldest lost, in order
    assert deserialize_message(payload, JointState).position.tolist() == [0.0, 1.0, 2.0]


def test_the_url_comes_before_the_run_and_the_run_waits_for_a_client(domain_id):
    port = free_port()
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    stack = subprocess.Popen([sys.executable, "-m", "has_control.cli", "stack", "--duration", "1.5", "--foxglove",
                              str(port), "--foxglove-wait", "60"], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        first = stack.stdout.readline()
        assert first.startswith(f"serving live on ws://127.0.0.1:{port}")

        async def read():
            deadline = time.monotonic() + 60
            async with await _connect(port, deadline) as ws:
                channels = await _advertised(ws, {"/state"}, deadline)
                await _subscribe(ws, channels["/state"], 1)
                frames = []
                while len(frames) < 100:
                    msg = await asyncio.wait_for(ws.recv(), max(deadline - time.monotonic(), 0.01))
                    if isinstance(msg, bytes):
                        frames.append(_message_data(msg))
                return frames
        frames = asyncio.run(read())
        out, err = stack.communicate(timeout=120)
    finally:
        stack.kill()
    assert stack.returncode == 0, err
    assert frames[0][1] < 100 * 300_000                  # the client saw the run from its start
    assert "J = " in out
