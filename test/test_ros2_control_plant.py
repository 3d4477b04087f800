"""The plant in its ros2_control layout against the controller in ros2_control mode,
in two processes, and an external recorder of the documented recording QoS in a
third."""
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import spin_until
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter

from has_control.config import with_horizon
from has_control.core.episode import Col, simulate
from has_control.core.params import Config
from has_control.nodes.plant_node import PlantNode

pytestmark = [pytest.mark.ros]

#: An external recorder: every message of a topic, by the recording QoS, in a process of its own;
#: prints the number of distinct samples (by stamp) and of messages once it has them all or the run is over.
RECORDER = """
import struct, sys, time
import rclpy
from rclpy.experimental import EventsExecutor
from sensor_msgs.msg import JointState
from has_control.nodes.runtime import RECORDING_QOS
topic, n, step = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rclpy.init()
node = rclpy.create_node("external_recorder")
seen, count, last = set(), [0], [time.monotonic()]
def take(data):
    sec, nsec = struct.unpack_from("<iI", data, 4)
    seen.add((sec * 1_000_000_000 + nsec) // step)
    count[0] += 1
    last[0] = time.monotonic()
node.create_subscription(JointState, topic, take, RECORDING_QOS, raw=True)
ex = EventsExecutor()
ex.add_node(node)
print("ready", flush=True)
end = time.monotonic() + 900
# until every sample is in, or the last one is and nothing came for 5 s (nothing more will)
while time.monotonic() < end and len(seen) < n and not (n - 1 in seen and time.monotonic() - last[0] > 5.0):
    ex.spin_once(timeout_sec=0.1)
print(len(seen), count[0], flush=True)
"""


@pytest.mark.parametrize("interface, horizon", [
    ("ros2_control", 1.5),
    pytest.param("ros2_control", 10.0, marks=pytest.mark.slow),
    pytest.param("has_control", 10.0, marks=pytest.mark.slow),
])
def test_plant_and_controller_in_two_processes_give_the_library_run_and_a_recorder_gets_every_state(
        context, domain_id, interface, horizon):
    cfg = with_horizon(Config(), horizon)
    n, step = cfg.episode.samples, cfg.episode.step_ns
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain_id)}
    controller = subprocess.Popen([sys.executable, "-m", "has_control.cli", "controller", "--ros-args",
                                   "-p", f"interface:={interface}", "-p", "publish_internals:=false"],
                                  env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    topic = "/joint_states" if interface == "ros2_control" else "/state"
    recorder = subprocess.Popen([sys.executable, "-c", RECORDER, topic, str(n), str(step)], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[
        Parameter("interface", value=interface), Parameter("samples", value=n),
        Parameter("command_timeout", value=5.0), Parameter("startup_timeout", value=60.0)])
    plant.process.log = []
    ex.add_node(plant)
    try:
        assert recorder.stdout.readline().strip() == "ready", recorder.stderr.read()
        assert spin_until(ex, lambda: plant.connected() and plant.state_pub.get_subscription_count() >= 2, 120)
        plant.start()
        plant.run(ex)
        assert plant.finished and plant.sample == n
        assert plant.failsafe_events == 0 and plant.conflicts == 0 and plant.malformed_commands == 0
        ref = simulate(cfg)
        log = np.array(plant.process.log)                           # sample, y, ydot, P1, P2, u
        np.testing.assert_array_equal(log[:, 0], np.arange(n))
        for k, col in enumerate((Col.y, Col.ydot, Col.P1, Col.P2, Col.u), start=1):
            np.testing.assert_array_equal(log[:, k], ref.data[:, col])     # the library's run, bit for bit
        out, err = recorder.communicate(timeout=300)
        samples, messages = map(int, out.split())
        assert samples == n, (samples, messages, err[-2000:])              # every state, none lost
    finally:
        for p in (controller, recorder):
            if p.poll() is None:
                p.kill()
                p.wait()
        ex.shutdown()
        plant.destroy_node()
