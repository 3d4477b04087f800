"""The controller node: the adaptive back-stepping law on every state it receives.

Each state arrives as serialized bytes; one compiled call
(:func:`has_control.wire.steps.controller_sample`) decodes it, runs the one
implementation (:func:`~has_control.core.abc_controller.abc_law`, ``adapt``,
:func:`~has_control.core.reference.reference`) with the sample time taken from the
state's stamp, and encodes the valve command, stamped like the state it
answers, and the internals. A state that goes back in time (a second plant on
the topic) is counted as a conflict and logged as an error. A state of
another layout, off the sample grid or with a non-finite value is refused and counted (``malformed_states``, logged
at most every 5 s): it never reaches the estimates.

Parameters: ``gains.k1..k3`` [1/s] (> 0), ``adaptation.*``, ``reference.*``,
the model ``actuator.*``, ``simulation.step`` and ``noise.*``: the seeded
measurement noise the law reads on top of each state it receives (the state
topic carries the plant's true state, which the trace and a bag keep); with
``noise.added_by: plant`` the states arrive as the plant's sensors read them
and the law adds nothing. A parameter set that the
core rejects (k1 = -1, NaN, a_min > a_max, ...) is refused with the reason
and the old values stay; accepted changes apply from the next sample.
``simulation.*`` (the step must be the plant's) is read-only after start-up.

Topics (layouts in :mod:`has_control.wire.topics`): ``state`` (in), ``command``
(out), and std_msgs/Float64MultiArray leading with the sample's simulation
time t [s] (the type has no header): ``~/controller_state`` [t, e1 [m],
e2 [m/s], e3 [N], â1, â2, x1d [m]], ``~/reference`` [t, x1d [m], ẋ1d [m/s],
ẍ1d [m/s²], x1d⁽³⁾ [m/s³]] (both when ``publish_internals``), and ``~/gains``
[t, k1, k2, k3] [1/s] (transient local), published at the first sample of each
run and whenever new gains take effect. Parameter ``foxglove_port``: serve
these topics live on a Foxglove WebSocket at this port of 127.0.0.1
(:mod:`has_control.nodes.foxglove`; 0: off). Service ``~/reset``
(std_srvs/Trigger): estimates back to â(0), the next state starts a new run.
"""
from __future__ import annotations

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from has_control.wire import steps
from has_control.core.episode import TRACE_COLUMNS, EpisodeArrays
from has_control.common.errors import ConfigError
from has_control.wire.topics import (
    COMMAND, COMMAND_LAYOUT, CONTROLLER_STATE, CONTROLLER_STATE_LAYOUT, GAINS, GAINS_LAYOUT, REFERENCE,
    REFERENCE_LAYOUT, STATE,
)
from has_control.wire.codec import NOT_FINITE, get_stamp
from has_control.nodes.foxglove import node_tap
from has_control.nodes.runtime import CONTROL_QOS, node_main, qos, raw_publish, spin, trigger_service
from has_control.nodes.parameters import config_from_node, declare_config

PREFIXES = ("actuator.", "simulation.", "gains.", "adaptation.", "reference.", "noise.")


class ControllerNode(Node):
    def __init__(self, name: str = "controller", tap=None, **kwargs):
        """``tap(topic)``: a function taking every message published on ``topic`` (an in-process observer)."""
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES, read_only=("simulation.",))
        self.declare_parameter("publish_internals", True)
        self._mem = np.zeros(steps.CONTROLLER_MEMORY)
        self._command = COMMAND_LAYOUT.buffer()
        self._internals = CONTROLLER_STATE_LAYOUT.buffer()
        self._reference = REFERENCE_LAYOUT.buffer()
        self.trace = np.zeros((0, len(TRACE_COLUMNS)))
        self.malformed_states = 0
        self.conflicts = 0
        self._apply(config_from_node(self, PREFIXES))
        self._pending = None
        self.reset()
        steps.warm_up()                         # compile or load the step before joining the graph
        self.add_on_set_parameters_callback(self._on_set_parameters)
        tap, self.live_view = node_tap(self, tap)      # parameter foxglove_port
        self.command_pub = self.create_publisher(JointState, COMMAND, CONTROL_QOS)
        self.internals_pub = self.create_publisher(Float64MultiArray, "~/controller_state", qos(CONTROLLER_STATE))
        self.reference_pub = self.create_publisher(Float64MultiArray, "~/reference", qos(REFERENCE))
        self.gains_pub = self.create_publisher(Float64MultiArray, "~/gains", qos(GAINS))
        self._publish_command = raw_publish(self.command_pub, tap)
        self._publish_internals = raw_publish(self.internals_pub, tap)
        self._publish_reference = raw_publish(self.reference_pub, tap)
        self._publish_gains = raw_publish(self.gains_pub, tap)
        self._state_topic = self.create_subscription(JointState, STATE, self._on_state, CONTROL_QOS,
                                                     raw=True).topic_name
        trigger_service(self, "~/reset", self.reset, "estimates reset to adaptation.initial")
        self.publish_internals = bool(self.get_parameter("publish_internals").value)

    def _apply(self, cfg, arr: EpisodeArrays | None = None) -> None:
        self.cfg = cfg
        arr = arr or EpisodeArrays.from_config(cfg)
        self.ap, self.cp, self.rp = arr.actuator, arr.adaptation, arr.reference
        # noise.added_by plant: the states arrive measured already; the law adds nothing
        self.sp = arr.sensor if cfg.noise.added_by == "controller" else np.zeros_like(arr.sensor)
        self.seed = arr.seed
        self.k = cfg.gains.as_tuple()
        self._gains = np.array(self.k)
        self.dt = cfg.episode.step
        self.step_ns = int(round(self.dt * 1e9))

    def reset(self) -> None:
        """Estimates back to â(0); the next sample starts a new run."""
        self._mem[steps.A1_HAT], self._mem[steps.A2_HAT] = self.cfg.adaptation.initial
        self._mem[steps.X3D_PREV] = self._mem[steps.HAS_PREV] = 0.0
        self._last_state = self._last_command = b""
        self._announce = True                   # publish the gains in force at the next sample

    @property
    def a1_hat(self) -> float:
        return float(self._mem[steps.A1_HAT])

    @a1_hat.setter
    def a1_hat(self, value: float) -> None:
        self._mem[steps.A1_HAT] = value

    @property
    def a2_hat(self) -> float:
        return float(self._mem[steps.A2_HAT])

    def record_trace(self, samples: int) -> np.ndarray:
        """Keep rows 0..samples-1 of the run (TRACE_COLUMNS) in a preallocated array."""
        self.trace = np.full((samples, len(TRACE_COLUMNS)), np.nan)
        return self.trace

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
        self._pending = (cfg, EpisodeArrays.from_config(cfg))    # built here (a road's table), applied next sample
        return SetParametersResult(successful=True)

    # --- control loop: read -> update -> write --------------------------------
    def _sample(self, data: bytes) -> int:
        """Sample index of a serialized state's stamp."""
        return int(get_stamp(data)) // self.step_ns if len(data) >= 12 else -1

    def _on_state(self, data) -> None:
        if not isinstance(data, bytes):          # a message object (in-process callers, tests)
            from rclpy.serialization import serialize_message
            data = serialize_message(data)
        if data == self._last_state:             # the plant sent it again: the same answer (not to observers)
            self.command_pub.publish(self._last_command)
            return
        if self._last_state and 0 < self._sample(data) <= self._sample(self._last_state):
            self.conflicts += 1                  # a second plant on the topic, or time going backwards
            self.get_logger().error(
                f"state for sample {self._sample(data)} after sample {self._sample(self._last_state)}: "
                f"{self.count_publishers(self._state_topic)} publishers on {self._state_topic}; "
                f"{self.conflicts} conflicting states so far", throttle_duration_sec=5.0)
        if self._pending is not None:
            self._apply(*self._pending)
            self._pending = None
            self._announce = True
        i = steps.controller_sample(data, self._mem, self._gains, self.ap, self.cp, self.rp, self.sp, self.seed,
                                    self.dt, self.step_ns, self._command, self._internals, self._reference, self.trace)
        if i < 0:
            self.malformed_states += 1
            what = "a non-finite value" if i == NOT_FINITE else "not the plant's JointState on the sample grid"
            self.get_logger().warning(f"refused a state ({what}); {self.malformed_states} so far",
                                      throttle_duration_sec=5.0)
            return
        if self._announce:
            self._publish_gains(GAINS_LAYOUT.encode([i * self.dt, *self.k]))
            self._announce = False
        self._last_state, self._last_command = data, bytes(self._command)
        self._publish_command(self._last_command)
        if self.publish_internals:
            self._publish_internals(bytes(self._internals))
            self._publish_reference(bytes(self._reference))


def main(args=None):
    node_main(args, ControllerNode, lambda executor, node: spin(executor))
