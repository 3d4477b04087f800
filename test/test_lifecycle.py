"""Managed plant and controller (lifecycle_msgs services), the controller's
ros2_control interface against a hardware-like node, and its /diagnostics."""
import functools
import time

import numpy as np
import pytest
from conftest import spin_until
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from has_control.config import with_horizon
from has_control.core.episode import simulate
from has_control.core.params import Config
from has_control.nodes.controller_node import ControllerNode
from has_control.nodes.plant_node import PlantNode
from has_control.wire import steps
from has_control.wire.topics import CLOCK_LAYOUT, STATE_LAYOUT

pytestmark = [pytest.mark.ros]

#: The hardware's joints: other names than the plant's, extra joints around them.
JOINTS = ["wheel_hub", "rod", "cap_side", "rod_side", "pump"]
MAPPING = ["rod/position", "rod/velocity", "cap_side/effort", "rod_side/effort"]
ROS2_CONTROL = [Parameter("interface", value="ros2_control"), Parameter("state_interfaces", value=MAPPING)]
#: These tests spin the executor in 1 ms steps (the other test files in 10 ms).
_spin_until = functools.partial(spin_until, step=0.001)


def _call(ex, client, request, seconds=30.0):
    assert client.wait_for_service(timeout_sec=10.0), client.srv_name
    fut = client.call_async(request)
    assert _spin_until(ex, fut.done, seconds), client.srv_name
    return fut.result()


def _lifecycle(ex, node, name):
    get = node.create_client(GetState, f"{name}/get_state")
    change = node.create_client(ChangeState, f"{name}/change_state")

    def state():
        return _call(ex, get, GetState.Request()).current_state.label

    def transition(label):
        req = ChangeState.Request()
        req.transition.label = label
        return _call(ex, change, req).success
    return state, transition


def _joint_state(x, stamp_ns=0):
    """What a ros2_control system's joint_state_broadcaster publishes: the actuator as
    joints 'rod', 'cap_side', 'rod_side' among others, pressures as effort."""
    msg = JointState()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.name = JOINTS
    msg.position = [0.25, float(x[0]), 1e-4, 2e-4, 0.0]
    msg.velocity = [0.0, float(x[1]), 0.0, 0.0, 3.0]
    msg.effort = [0.0, 1.0, float(x[2]), float(x[3]), 2.1e7]
    return msg


class Hardware:
    """A hardware-like node that speaks only the ros2_control conventions:
    sensor_msgs/JointState on /joint_states out, std_msgs/Float64MultiArray on
    /forward_command_controller/commands in. It steps the library's plant every
    0.3 ms; a command later than that is waited for (counted in ``late``), so
    what is compared is the data, never the machine's timing. Its states are
    stamped, as a controller manager stamps them, at the period's sample times."""

    def __init__(self, context, cfg):
        self.node = rclpy.create_node("hardware", context=context)
        self.pub = self.node.create_publisher(JointState, "/joint_states", QoSProfile(depth=10))
        self.commands = []
        self.node.create_subscription(Float64MultiArray, "/forward_command_controller/commands",
                                      lambda m: self.commands.append(list(m.data)), QoSProfile(depth=10))
        self.cfg = cfg
        self.x = np.append(cfg.plant.actuator(cfg.actuator).initial_state(), 0.0)
        self.late = 0

    def run(self, ex, samples):
        cfg = self.cfg
        ap = cfg.plant.as_array(cfg.actuator)
        step_ns = int(round(cfg.episode.step * 1e9))
        state, clock, scr = STATE_LAYOUT.buffer(), CLOCK_LAYOUT.buffer(), steps.scratch()
        ys, us = [], []
        t0 = time.perf_counter_ns()
        epoch = time.time_ns()                   # stamps of the control period, from the wall clock's start
        for i in range(samples):
            due = t0 + i * step_ns
            while time.perf_counter_ns() < due:
                pass
            ys.append(float(self.x[0]))
            self.pub.publish(_joint_state(self.x, epoch + i * step_ns))
            if not _spin_until(ex, lambda: len(self.commands) > i, 2.0 if i else 20.0):
                raise AssertionError(f"no command for sample {i}")
            if time.perf_counter_ns() > due + step_ns:
                self.late += 1
            u = self.commands[i][0]
            us.append(u)
            steps.plant_sample(self.x, u, ap, cfg.episode.step, cfg.episode.y_limit, i + 1, step_ns,
                               state, clock, scr)
        return np.array(ys), np.array(us)


def test_ros2_control_mode_tracks_and_equals_the_library(context):
    cfg = with_horizon(Config(), 1.5)
    n = cfg.episode.samples
    ex = EventsExecutor(context=context)
    controller = ControllerNode(context=context, parameter_overrides=ROS2_CONTROL)
    controller.record_trace(n)
    hw = Hardware(context, cfg)
    for node in (controller, hw.node):
        ex.add_node(node)
    try:
        assert _spin_until(ex, lambda: hw.pub.get_subscription_count()
                           and controller.command_pub.get_subscription_count(), 20.0)
        ys, us = hw.run(ex, n)
    finally:
        ex.shutdown()
        controller.destroy_node()
        hw.node.destroy_node()
    ref = simulate(cfg)
    assert all(len(c) == 1 for c in hw.commands)                   # [u], what a forward_command_controller takes
    np.testing.assert_array_equal(us, ref.data[:, 6])               # the library's commands, bit for bit
    np.testing.assert_array_equal(ys, ref.data[:, 2])
    np.testing.assert_array_equal(controller.trace, ref.data)
    e1 = ref.data[:, 7]
    assert np.max(np.abs(e1[n // 2:])) < 0.05 * np.max(np.abs(ref.data[:, 1]))   # it tracks
    assert controller.states_answered == n and controller.malformed_states == 0


def test_a_joint_state_without_the_mapped_joints_is_refused_and_counted(context):
    controller = ControllerNode(context=context, parameter_overrides=ROS2_CONTROL)
    try:
        msg = _joint_state([0.0, 0.0, 1e6, 1e6])
        msg.name = ["wheel_hub", "piston", "cap_side", "rod_side", "pump"]          # no 'rod'
        controller._on_joint_state(msg)
        msg = _joint_state([float("nan"), 0.0, 1e6, 1e6])
        controller._on_joint_state(msg)
        assert controller.malformed_states == 2 and controller.states_answered == 0
        controller._on_joint_state(_joint_state(Config().actuator.initial_state()))
        assert controller.states_answered == 1
    finally:
        controller.destroy_node()


@pytest.mark.parametrize("mapping", [["rod/pressure", "rod/velocity", "cap_side/effort", "rod_side/effort"],
                                     ["rod/position"]])
def test_a_bad_mapping_is_refused_at_configure(context, mapping):
    with pytest.raises(ValueError, match="state_interfaces"):
        ControllerNode(context=context, parameter_overrides=[Parameter("interface", value="ros2_control"),
                                                             Parameter("state_interfaces", value=mapping)])


def test_controller_lifecycle_through_the_standard_services(context):
    ex = EventsExecutor(context=context)
    controller = ControllerNode(context=context, parameter_overrides=ROS2_CONTROL + [
        Parameter("autostart", value=False)])
    operator = rclpy.create_node("operator", context=context)
    commands, diagnostics = [], []
    operator.create_subscription(Float64MultiArray, "/forward_command_controller/commands",
                                 lambda m: commands.append(list(m.data)), QoSProfile(depth=10))
    operator.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, QoSProfile(depth=10))
    states = operator.create_publisher(JointState, "/joint_states", QoSProfile(depth=10))
    for node in (controller, operator):
        ex.add_node(node)
    state, transition = _lifecycle(ex, operator, "/controller")
    x0 = Config().actuator.initial_state()
    try:
        assert state() == "unconfigured"
        assert operator.count_publishers("/forward_command_controller/commands") == 0
        assert transition("configure") and state() == "inactive"
        assert _spin_until(ex, lambda: states.get_subscription_count()
                           and controller.command_pub.get_subscription_count(), 20)
        states.publish(_joint_state(x0))
        _spin_until(ex, lambda: commands, 0.5)
        assert commands == [] and controller.states_answered == 0       # inactive: not answering
        assert transition("activate") and state() == "active"
        states.publish(_joint_state(x0))
        assert _spin_until(ex, lambda: commands, 10)
        assert commands == [[simulate(with_horizon(Config(), 1.5)).data[0, 6]]]
        assert _spin_until(ex, lambda: any(s.name == "/controller: control law" for d in diagnostics
                                           for s in d.status), 5)
        law = [s for d in diagnostics for s in d.status if s.name == "/controller: control law"][-1]
        values = {kv.key: kv.value for kv in law.values}
        assert values["states_answered"] == "1" and values["estimates_in_bounds"] == "True"
        assert {"late", "malformed_states", "conflicts"} <= set(values)
        assert transition("deactivate") and state() == "inactive"
        assert _spin_until(ex, lambda: len(commands) == 2, 10) and commands[1] == [0.0]   # valve centred
        states.publish(_joint_state(x0))
        _spin_until(ex, lambda: len(commands) > 2, 0.5)
        assert len(commands) == 2
        assert transition("cleanup") and state() == "unconfigured"
        assert _spin_until(ex, lambda: operator.count_publishers("/forward_command_controller/commands") == 0, 5)
        assert transition("shutdown") and state() == "finalized"
    finally:
        ex.shutdown()
        controller.destroy_node()
        operator.destroy_node()


def test_a_refused_configure_leaves_the_node_unconfigured(context):
    ex = EventsExecutor(context=context)
    controller = ControllerNode(context=context, parameter_overrides=[
        Parameter("autostart", value=False), Parameter("interface", value="ethercat")])
    operator = rclpy.create_node("operator", context=context)
    for node in (controller, operator):
        ex.add_node(node)
    state, transition = _lifecycle(ex, operator, "/controller")
    try:
        assert not transition("configure") and state() == "unconfigured"
        assert "interface" in controller.configure_error
    finally:
        ex.shutdown()
        controller.destroy_node()
        operator.destroy_node()


def test_plant_lifecycle_runs_only_while_active(context):
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[Parameter("autostart", value=False)])
    controller = ControllerNode(context=context)
    operator = rclpy.create_node("operator", context=context)
    for node in (plant, controller, operator):
        ex.add_node(node)
    state, transition = _lifecycle(ex, operator, "/plant")
    start = operator.create_client(Trigger, "/plant/start")
    try:
        assert state() == "unconfigured" and operator.count_publishers("/state") == 0
        assert transition("configure") and state() == "inactive"
        assert _spin_until(ex, plant.connected, 20)
        _call(ex, start, Trigger.Request())
        _spin_until(ex, lambda: plant.sample > 0, 0.3)
        assert plant.sample == 0                                        # inactive: no episode
        assert transition("activate") and state() == "active"
        _call(ex, start, Trigger.Request())
        assert _spin_until(ex, lambda: plant.sample >= 200, 20)
        assert transition("deactivate") and state() == "inactive"
        stopped = plant.sample
        assert plant.finished and plant.command_u == 0.0                 # ended, valve centred
        _spin_until(ex, lambda: plant.sample > stopped, 0.3)
        assert plant.sample == stopped
        assert transition("cleanup") and state() == "unconfigured"
        assert _spin_until(ex, lambda: operator.count_publishers("/state") == 0, 5)
        assert transition("shutdown") and state() == "finalized"
    finally:
        ex.shutdown()
        for node in (plant, controller, operator):
            node.destroy_node()


def test_plant_start_after_an_episode_runs_an_episode_and_a_reset_plant_meets_fresh_estimates(context):
    """~/start after a finished episode once ran one sample while answering "episode
    started"; after ~/reset the controller's estimates carried over into the new run."""
    n = 300
    ex = EventsExecutor(context=context)
    plant = PlantNode(context=context, parameter_overrides=[Parameter("samples", value=n),
                                                            Parameter("keep_alive", value=True)])
    controller = ControllerNode(context=context)
    controller.record_trace(n)
    operator = rclpy.create_node("operator", context=context)
    for node in (plant, controller, operator):
        ex.add_node(node)
    start, reset = (operator.create_client(Trigger, f"/plant/{s}") for s in ("start", "reset"))
    try:
        assert _spin_until(ex, plant.connected, 20)
        assert _call(ex, start, Trigger.Request()).success
        assert _spin_until(ex, lambda: plant.finished, 60) and plant.sample == n
        assert _call(ex, start, Trigger.Request()).message == "episode started"
        assert _spin_until(ex, lambda: plant.finished and plant.sample > n, 60)
        _spin_until(ex, lambda: False, 0.2)
        assert plant.sample == 2 * n                                   # a whole episode, not one sample
        moved = controller.a1_hat
        assert moved != 2600.0
        assert _call(ex, reset, Trigger.Request()).success and plant.sample == 0
        assert _call(ex, start, Trigger.Request()).success
        assert _spin_until(ex, lambda: plant.finished and plant.sample == n, 60)
        ref = simulate(with_horizon(Config(), 1.5))
        np.testing.assert_array_equal(controller.trace, ref.data[:n])   # the new run from a(0): the library's
    finally:
        ex.shutdown()
        for node in (plant, controller, operator):
            node.destroy_node()


def test_two_publishers_on_joint_states_are_conflicts_not_consecutive_samples(context):
    """Two ros2_control systems on /joint_states with the same clock: each sample is answered
    once, the other system's state is counted as a conflict (and stale), never answered."""
    ex = EventsExecutor(context=context)
    controller = ControllerNode(context=context, parameter_overrides=ROS2_CONTROL)
    a, b = (rclpy.create_node(name, context=context) for name in ("system_a", "system_b"))
    pubs = [n.create_publisher(JointState, "/joint_states", QoSProfile(depth=10)) for n in (a, b)]
    for node in (controller, a, b):
        ex.add_node(node)
    x = Config().actuator.initial_state()
    epoch, step = time.time_ns(), 300_000
    try:
        assert _spin_until(ex, lambda: all(p.get_subscription_count() for p in pubs), 20)
        for i in range(10):
            pubs[0].publish(_joint_state(x, epoch + i * step))
            _spin_until(ex, lambda: controller.states_answered == i + 1, 10)      # the reader keeps the last one
            pubs[1].publish(_joint_state([x[0] + 1e-3, x[1], x[2], x[3]], epoch + i * step))
            _spin_until(ex, lambda: controller.conflicts == i + 1 and controller.states_answered == i + 1, 10)
            assert (controller.conflicts, controller.states_answered, controller.port.repeated) == (i + 1, i + 1, 0), i
        assert controller.port.stale == 10 and controller.port.missing == 0
    finally:
        ex.shutdown()
        for node in (controller, a, b):
            node.destroy_node()
