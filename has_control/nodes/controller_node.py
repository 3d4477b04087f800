"""The controller node: the adaptive back-stepping law on every state it receives.

Calls :func:`has_control.abc_controller.abc_law` and ``adapt`` (the one
implementation) with the sample time taken from the state's stamp, and
publishes the valve command stamped like the state it answers.

Parameters: ``gains.k1..k3`` [1/s] (> 0), ``adaptation.*``, ``reference.*``,
the model ``actuator.*`` and ``simulation.step``. A parameter set that the
core rejects (k1 = -1, NaN, a_min > a_max, ...) is refused with the reason
and the old values stay; accepted changes apply from the next sample.

Topics: ``state`` (in), ``command`` (out); std_msgs/Float64MultiArray, each
leading with the sample's simulation time t [s] (the type has no header):
``~/controller_state`` [t, e1 [m], e2 [m/s], e3 [N], â1, â2, x1d [m]],
``~/reference`` [t, x1d [m], ẋ1d [m/s], ẍ1d [m/s²], x1d⁽³⁾ [m/s³]] (both when
``publish_internals``), and ``~/gains`` [t, k1, k2, k3] [1/s] (transient
local), published at the first sample of each run and whenever new gains
take effect. Service ``~/reset`` (std_srvs/Trigger): estimates back to â(0),
the next state starts a new run.
"""
from __future__ import annotations

import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from ..abc_controller import abc_law, adapt
from ..errors import ConfigError
from ..episode import EpisodeArrays
from ..reference import reference
from .messages import CONTROL_QOS, LATCHED_QOS, command_message, sample_of, state_of, trigger_service
from .parameters import config_from_node, declare_config

PREFIXES = ("actuator.", "simulation.", "gains.", "adaptation.", "reference.")


class ControllerNode(Node):
    def __init__(self, name: str = "controller", **kwargs):
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES)
        self.declare_parameter("publish_internals", True)
        self._apply(config_from_node(self, PREFIXES))
        self._pending = None
        self.reset()
        self._warm_up()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.command_pub = self.create_publisher(JointState, "command", CONTROL_QOS)
        self.internals_pub = self.create_publisher(Float64MultiArray, "~/controller_state", 10)
        self.reference_pub = self.create_publisher(Float64MultiArray, "~/reference", 10)
        self.gains_pub = self.create_publisher(Float64MultiArray, "~/gains", LATCHED_QOS)
        self.create_subscription(JointState, "state", self._on_state, CONTROL_QOS)
        trigger_service(self, "~/reset", self.reset, "estimates reset to adaptation.initial")
        self.publish_internals = bool(self.get_parameter("publish_internals").value)
        self.log: list[tuple] | None = None

    def _apply(self, cfg) -> None:
        self.cfg = cfg
        arr = EpisodeArrays.from_config(cfg)
        self.ap, self.cp, self.rp = arr.actuator, arr.adaptation, arr.reference
        self.k = cfg.gains.as_tuple()
        self.dt = cfg.episode.step
        self.step_ns = int(round(self.dt * 1e9))

    def reset(self) -> None:
        """Estimates back to â(0); the next sample starts a new run."""
        self.a1_hat, self.a2_hat = self.cfg.adaptation.initial
        self.x3d_prev = 0.0
        self.has_prev = False
        self._announce = True                   # publish the gains in force at the next sample

    def _warm_up(self) -> None:
        """Compile (or load) the control law before joining the graph."""
        x = self.cfg.actuator.initial_state()
        r = reference(self.rp, 0.0)
        out = abc_law(x[0], x[1], x[2], x[3], self.a1_hat, self.a2_hat, 0.0, False, *r,
                      *self.k, self.ap, self.cp, self.dt)
        adapt(self.a1_hat, self.a2_hat, out[4], out[5], self.cp, self.dt)

    # --- parameters --------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        changes = {p.name: p.value for p in params if p.name.startswith(PREFIXES)}
        if not changes:
            return SetParametersResult(successful=True)
        try:
            cfg = config_from_node(self, PREFIXES, overrides=changes)
        except ConfigError as exc:
            reason = str(exc)
            self.get_logger().warning(f"rejected {sorted(changes)}: {reason}")
            return SetParametersResult(successful=False, reason=reason)
        self._pending = cfg                      # applies from the next sample
        return SetParametersResult(successful=True)

    # --- control loop ------------------------------------------------------
    def _on_state(self, msg: JointState) -> None:
        if self._pending is not None:
            self._apply(self._pending)
            self._pending = None
            self._announce = True
        i = sample_of(msg.header.stamp, self.step_ns)
        t = i * self.dt
        if self._announce:
            self.gains_pub.publish(Float64MultiArray(data=[t, *self.k]))
            self._announce = False
        x1, x2, p1, p2 = state_of(msg)
        r0, r1, r2, r3 = reference(self.rp, t)
        k1, k2, k3 = self.k
        u, e1, e2, e3, rate1, rate2, x3d = abc_law(
            x1, x2, p1, p2, self.a1_hat, self.a2_hat, self.x3d_prev, self.has_prev,
            r0, r1, r2, r3, k1, k2, k3, self.ap, self.cp, self.dt)
        self.command_pub.publish(command_message(msg, u))
        if self.log is not None:
            self.log.append((t, r0, x1, x2, p1, p2, u, e1, e2, e3, self.a1_hat, self.a2_hat))
        if self.publish_internals:
            self.internals_pub.publish(Float64MultiArray(data=[t, e1, e2, e3, self.a1_hat, self.a2_hat, r0]))
            self.reference_pub.publish(Float64MultiArray(data=[t, r0, r1, r2, r3]))
        self.a1_hat, self.a2_hat = adapt(self.a1_hat, self.a2_hat, rate1, rate2, self.cp, self.dt)
        self.x3d_prev = x3d
        self.has_prev = True


def main(args=None):
    rclpy.init(args=args)
    node = ControllerNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
