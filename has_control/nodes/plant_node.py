"""The plant node: simulates the actuator at one 0.3 ms step per sample.

Lock-step mode (default): publish state i, wait for command i, advance with
:func:`has_control.actuator.plant_step` (the one implementation), publish
state i + 1. A run through the graph therefore equals the in-process trace.
If no command arrives within ``command_timeout`` seconds of wall time, the
fail-safe applies u = 0 (valve centred) to that sample, warns once per
outage and counts the event; control resumes when commands return.

Topics: ``state`` (sensor_msgs/JointState, out), ``command``
(sensor_msgs/JointState, in), ``/clock`` (rosgraph_msgs/Clock, out).
Services: ``~/reset`` (std_srvs/Trigger): back to the initial state, sample 0.
"""
from __future__ import annotations

import time

import numpy as np
import rclpy
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from ..actuator import plant_step
from .messages import CONTROL_QOS, reset_service, sample_of, stamp, state_message
from .parameters import config_from_node, declare_config

PREFIXES = ("actuator.", "simulation.")


class PlantNode(Node):
    def __init__(self, name: str = "plant", **kwargs):
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES)
        self.declare_parameter("mode", "lockstep")
        self.declare_parameter("command_timeout", 0.5)
        self.declare_parameter("samples", 0)        # 0: run until stopped
        cfg = config_from_node(self, PREFIXES)
        self.actuator = cfg.actuator
        self.ap = cfg.actuator.as_array()
        self.step = cfg.episode.step
        self.step_ns = int(round(self.step * 1e9))
        self.y_limit = cfg.episode.y_limit
        self.samples = int(self.get_parameter("samples").value)
        self.timeout = float(self.get_parameter("command_timeout").value)
        self.mode = self.get_parameter("mode").value
        if self.mode != "lockstep":
            raise ValueError(f"parameter mode = {self.mode!r}: only 'lockstep' is implemented")
        x0 = self.actuator.initial_state()
        plant_step(x0[0], x0[1], x0[2], x0[3], 0.0, self.ap, self.step)   # compile before joining the graph
        self.state_pub = self.create_publisher(JointState, "state", CONTROL_QOS)
        self.clock_pub = self.create_publisher(Clock, "/clock", 10)
        sub = self.create_subscription(JointState, "command", self._on_command, CONTROL_QOS)
        self._command_topic = sub.topic_name
        reset_service(self, self._reset_state, "plant reset to the initial state, sample 0")
        self.failsafe_events = 0
        self.started_at = self.run_seconds = 0.0
        self._in_outage = False
        self.finished = False
        self.log: list[tuple[int, float, float, float, float, float]] | None = None
        self._reset_state()
        self._watchdog = self.create_timer(max(self.timeout / 4, 0.01), self._check_deadline)

    # --- state -------------------------------------------------------------
    def _reset_state(self) -> None:
        self.x = self.actuator.initial_state()
        self.sample = 0
        self.finished = False
        self._last_publish = time.monotonic()
        self._published = False

    def start(self) -> None:
        """Publish state 0 (or re-publish the current one)."""
        self.started_at = time.perf_counter()
        self._publish()

    def connected(self) -> bool:
        """Both directions of the loop have a peer (a controller is listening and talking)."""
        return bool(self.state_pub.get_subscription_count()
                    and self.count_publishers(self._command_topic))

    def _publish(self) -> None:
        self.clock_pub.publish(Clock(clock=stamp(self.sample, self.step_ns)))
        self.state_pub.publish(state_message(self.sample, self.step_ns, self.x, self.actuator))
        self._last_publish = time.monotonic()
        self._published = True

    def _advance(self, u: float) -> None:
        if self.log is not None:
            self.log.append((self.sample, *map(float, self.x), u))
        y, v, p1, p2 = plant_step(self.x[0], self.x[1], self.x[2], self.x[3], u, self.ap, self.step)
        self.x = np.array([y, v, p1, p2])
        self.sample += 1
        if self.samples and self.sample >= self.samples:
            self.finished = True
            self.run_seconds = time.perf_counter() - self.started_at
            return
        if not np.all(np.isfinite(self.x)) or abs(y) > self.y_limit:
            self.get_logger().error(f"diverged at sample {self.sample}: y = {y:.4g} m")
            self.finished = True
            return
        self._publish()

    # --- callbacks ---------------------------------------------------------
    def _on_command(self, msg: JointState) -> None:
        if self.finished or sample_of(msg.header.stamp, self.step_ns) != self.sample:
            return                                   # stale or early: not the sample we wait on
        if self._in_outage:
            self.get_logger().info(f"commands are back at sample {self.sample}")
            self._in_outage = False
        self._advance(float(msg.position[0]))

    def _check_deadline(self) -> None:
        if self.finished or not self._published:
            return
        if time.monotonic() - self._last_publish > self.timeout:
            self.failsafe_events += 1
            if not self._in_outage:
                self.get_logger().warning(
                    f"no command for sample {self.sample} within {self.timeout:g} s: "
                    "valve centred (u = 0) until commands return")
                self._in_outage = True
            self._advance(0.0)


def main(args=None):
    rclpy.init(args=args)
    node = PlantNode()
    try:
        while rclpy.ok() and not node.connected():
            rclpy.spin_once(node, timeout_sec=0.05)
        node.get_logger().info("controller connected: starting the run")
        node.start()
        while rclpy.ok() and not node.finished:
            rclpy.spin_once(node, timeout_sec=0.1)
        if node.finished:
            node.get_logger().info(
                f"finished {node.sample} samples at t = {node.sample * node.step:.4f} s: "
                f"y = {node.x[0]:.9e} m, fail-safe events = {node.failsafe_events}, "
                f"{node.sample / node.run_seconds:.0f} samples/s")
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
