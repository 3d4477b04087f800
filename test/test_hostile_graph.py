"""Hostile input on the real graph: no node dies of a message, no silent wrong number."""
import math
import subprocess
import sys
import time

import numpy as np
import pytest
import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState

from has_control.core.episode import simulate

from has_control.config import with_horizon
from has_control.common.errors import HasControlError
from has_control.nodes.controller_node import ControllerNode
from has_control.nodes.runtime import CONTROL_QOS, state_message
from has_control.nodes.plant_node import PlantNode
from has_control.nodes.stack import run_stack
from has_control.core.params import Config

from conftest import spin_until

pytestmark = [pytest.mark.ros]


def test_malformed_and_non_finite_messages_are_counted_and_ignored(context):
    """Empty JointStates, NaN values and strangers' layouts reach neither the
    plant's state nor the controller's estimates; the loop then runs as the library's."""
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[Parameter("samples", value=2000)])
    controller = ControllerNode(context=context)
    controller.record_trace(2000)
    evil = rclpy.create_node("evil", context=context)
    to_plant = evil.create_publisher(JointState, "command", CONTROL_QOS)
    to_controller = evil.create_publisher(JointState, "state", CONTROL_QOS)
    for n in (plant, controller, evil):
        ex.add_node(n)
    assert spin_until(ex, lambda: to_plant.get_subscription_count() and to_controller.get_subscription_count(), 10)
    cfg = Config()
    nan_state = state_message(0, 300_000, [0.0, math.nan, 1e6, 1e6], cfg.actuator)
    for msg in (JointState(), JointState(name=["valve"], position=[math.nan]), JointState(name=["valve"])):
        to_plant.publish(msg)                            # keep-last 1: one at a time
        spin_until(ex, lambda: False, 0.1)
    for msg in (JointState(), nan_state, JointState(name=["x"], position=[1.0])):
        to_controller.publish(msg)
        spin_until(ex, lambda: False, 0.1)
    assert plant.malformed_commands == 3 and controller.malformed_states == 3
    assert plant.sample == 0 and np.all(np.isfinite(plant.x)) and controller.a1_hat == 2600.0
    assert spin_until(ex, plant.connected, 10)
    plant.start()
    assert spin_until(ex, lambda: plant.finished, 60)
    ref = simulate(with_horizon(cfg, 1.5))
    np.testing.assert_array_equal(controller.trace, ref.data[:2000])
    ex.shutdown()
    for n in (plant, controller, evil):
        n.destroy_node()


def test_a_second_controller_on_the_command_topic_fails_the_run_loudly(domain_id):
    """Another controller answers the same states with other gains: the stack
    refuses to report a number instead of scoring a mixture."""
    cmd = [sys.executable, "-m", "has_control.cli", "controller", "--ros-args", "-p", "publish_internals:=false",
           "-p", "gains.k1:=400.0"]
    import os
    other = subprocess.Popen(cmd, env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        probe_ctx = rclpy.Context()
        rclpy.init(context=probe_ctx, domain_id=domain_id)
        probe = rclpy.create_node("probe", context=probe_ctx)
        end = time.monotonic() + 60
        while time.monotonic() < end and not probe.count_publishers("/command"):
            time.sleep(0.05)                             # it is up and on the graph
        assert probe.count_publishers("/command")
        probe.destroy_node()
        rclpy.try_shutdown(context=probe_ctx)
        with pytest.raises(HasControlError, match="another node publishes on this loop's topics"):
            run_stack(with_horizon(Config(), 120.0), domain_id=domain_id)   # long enough to meet it; ends at it
    finally:
        other.kill()
        other.wait()


def test_runtime_changes_the_loop_cannot_take_are_refused(context):
    controller = ControllerNode(context=context)
    plant = PlantNode(context=context)
    try:
        res = controller.set_parameters([Parameter("simulation.step", value=1e-12)])[0]
        assert not res.successful and "simulation.step" in res.reason and controller.dt == 3e-4
        for name, value in (("samples", -5), ("command_timeout", -1.0), ("realtime_priority", 200)):
            res = plant.set_parameters([Parameter(name, value=value)])[0]
            assert not res.successful and name in res.reason
        assert plant.samples == 0 and plant.timeout == 0.5
    finally:
        controller.destroy_node()
        plant.destroy_node()


@pytest.mark.parametrize("node, args, culprit", [
    ("controller", ["-p", "gains.k1:=-1.0"], "gains.k1"),
    ("plant", ["-p", "samples:=-5"], "samples = -5"),
    ("plant", ["-p", "command_timeout:=-1.0"], "command_timeout = -1.0"),
    ("plant", ["-p", "mode:=fast"], "mode = 'fast'"),
])
def test_bad_start_up_parameters_end_in_one_line(node, args, culprit, domain_id):
    import os
    r = subprocess.run([sys.executable, "-m", "has_control.cli", node, "--ros-args", *args],
                       env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and culprit in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_a_signal_during_a_recorded_stack_leaves_a_clean_bag(tmp_path, signame, domain_id):
    import os
    import signal
    from has_control.bag import read_bag
    bag = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "has_control.cli", "stack", "--duration", "600", "--record", bag],
                         env={**os.environ, "ROS_DOMAIN_ID": str(domain_id)},
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    end = time.monotonic() + 120
    while time.monotonic() < end and not (bag / "run.mcap").exists():
        time.sleep(0.1)
    time.sleep(1.5)                                       # mid-run
    p.send_signal(getattr(signal, signame))
    err = p.communicate(timeout=60)[1]
    assert p.returncode == 130 and err.strip() == "has-control: interrupted"
    b = read_bag(bag)
    assert b.complete and (bag / "metadata.yaml").exists()
    n = b.count("/state")
    assert n > 1000 and b.count("/command") in (n - 1, n)  # every sample taken before the signal


def test_a_command_of_another_layout_is_read_by_name_only_on_the_sample_grid(context):
    """A valve JointState with a frame_id and extra joints is still a command; off the grid it is refused."""
    from rclpy.serialization import serialize_message
    plant = PlantNode(context=context)
    try:
        other = JointState(name=["spool_temperature", "valve"], position=[300.0, 2e-5])
        other.header.frame_id = "base"
        other.header.stamp.nanosec = 600_000                  # sample 2
        plant._on_command(serialize_message(other))
        assert (plant.command_sample, plant.command_u, plant.malformed_commands) == (2, 2e-5, 0)
        other.header.stamp.nanosec = 750_000                  # between samples 2 and 3
        plant._on_command(serialize_message(other))
        assert plant.command_sample == 2 and plant.malformed_commands == 1
    finally:
        plant.destroy_node()
