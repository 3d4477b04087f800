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
and the old values stay; accepted changes apply from the next sample (a
new road from the first sample after it is built, off the executor).
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

Managed node (:mod:`has_control.nodes.managed`): ``configure`` validates the
parameters, builds the tables and creates the topics; ``activate`` starts
answering (estimates at â(0), a new run); ``deactivate`` centres the valve (a
command u = 0 for the next sample) and stops answering; ``cleanup`` and
``shutdown`` release the topics. ``autostart`` (default true) does configure
and activate at start-up.

Interfaces (parameter ``interface``): ``has_control`` (default; the plant's
``state``/``command`` above) or ``ros2_control``: the state is read from the
``sensor_msgs/JointState`` topic ``joint_states_topic`` (default
``/joint_states``, what ros2_control's joint_state_broadcaster publishes) through
``state_interfaces``, four ``joint/interface`` entries for y [m], ẏ [m/s],
P1 [Pa], P2 [Pa] (interface: position, velocity or effort; other joints in the
message are ignored), and the valve command u [m] is written as
``std_msgs/Float64MultiArray`` ``[u]`` on ``command_topic`` (default
``/forward_command_controller/commands``, what a forward_command_controller
takes). Each state that arrives is answered at once, as sample i = the number
of states answered since activation (its time i·Δt); see docs/ros2_control.md.

``/diagnostics`` (once a second, name "<node>: control law"): states
answered, late (answers that took longer than one step Δt to compute),
malformed, conflicts and whether â1, â2 are within ``adaptation.lower..upper``.
"""

import gc
import math
import time

import threading

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from has_control.wire import steps
from has_control.core.episode import TRACE_COLUMNS, EpisodeArrays
from has_control.core.reference import road_cached
from has_control.common.errors import ConfigError
from has_control.wire.topics import (
    CLOCK_LAYOUT, COMMAND, COMMAND_LAYOUT, CONTROLLER_STATE, CONTROLLER_STATE_LAYOUT, FORWARD_COMMAND_LAYOUT, GAINS,
    GAINS_LAYOUT, REFERENCE, REFERENCE_LAYOUT, STATE, STATE_LAYOUT,
)
from has_control.wire.codec import NOT_FINITE, get_stamp
from has_control.wire.joint_mapping import (
    DEFAULT_COMMAND_TOPIC, DEFAULT_JOINT_STATES_TOPIC, DEFAULT_STATE_INTERFACES, parse_state_interfaces, resolve,
)
from has_control.nodes.live_tap import node_tap
from has_control.nodes.managed import autostart as bring_up_now, declare_autostart, refuse, state_label
from has_control.nodes.runtime import CONTROL_QOS, node_main, qos, raw_publish, spin, trigger_service
from has_control.nodes.parameters import config_from_node, declare_config

PREFIXES = ("actuator.", "simulation.", "gains.", "adaptation.", "reference.", "noise.")
INTERFACES = ("has_control", "ros2_control")
#: The controller's own parameters: (name, default, meaning and unit, read-only).
OWN_PARAMETERS = (
    ("publish_internals", True, "publish ~/controller_state and ~/reference every sample", False),
    ("interface", "has_control", "has_control (the plant's state/command JointStates) | ros2_control "
     "(JointState from joint_states_topic, Float64MultiArray [u] on command_topic)", True),
    ("joint_states_topic", DEFAULT_JOINT_STATES_TOPIC, "ros2_control: the sensor_msgs/JointState topic read", True),
    ("command_topic", DEFAULT_COMMAND_TOPIC,
     "ros2_control: the std_msgs/Float64MultiArray topic the valve command u [m] is written to", True),
    ("state_interfaces", list(DEFAULT_STATE_INTERFACES),
     "ros2_control: joint/interface of y [m], y_dot [m/s], P1 [Pa], P2 [Pa] "
     "(interface: position, velocity or effort)", True),
)


class ControllerNode(LifecycleNode):
    def __init__(self, name: str = "controller", tap=None, **kwargs):
        """``tap(topic)``: a function taking every message published on ``topic`` (an in-process observer)."""
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES, read_only=("simulation.",))
        for key, value, text, read_only in OWN_PARAMETERS:
            desc = ParameterDescriptor(description=text, read_only=read_only)
            if key == "interface":
                desc.additional_constraints = f"one of: {', '.join(INTERFACES)}"
            self.declare_parameter(key, value, desc)
        autostart = declare_autostart(self)
        self._mem = np.zeros(steps.CONTROLLER_MEMORY)
        self._command = COMMAND_LAYOUT.buffer()
        self._internals = CONTROLLER_STATE_LAYOUT.buffer()
        self._reference = REFERENCE_LAYOUT.buffer()
        self._state_buf, self._clock_buf = STATE_LAYOUT.buffer(), CLOCK_LAYOUT.buffer()
        self._x = np.zeros(5)
        self._scratch = steps.scratch()
        self.trace = np.zeros((0, len(TRACE_COLUMNS)))
        self.malformed_states = self.conflicts = self.states_answered = self.late = 0
        self.cfg = None
        self.configure_error = ""
        self.quiet = False                        # True: no "ready"/"inactive" lines (stack drives us)
        self.active = False
        self._pending = None
        self._entities: list = []
        self._state_topic = ""
        self._pending_lock = threading.Lock()
        self._generation = 0                    # accepted parameter sets: a road built for an old one is dropped
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._tap, self.live_view = node_tap(self, tap)      # parameter foxglove_port
        trigger_service(self, "~/reset", self.reset, "estimates reset to adaptation.initial")
        if autostart:
            bring_up_now(self)

    # --- lifecycle -----------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Validate the parameters, build the tables, create the topics."""
        try:
            interface = self.get_parameter("interface").value
            if interface not in INTERFACES:
                raise ValueError(f"parameter interface = {interface!r}: expected one of {', '.join(INTERFACES)}")
            mapping = parse_state_interfaces(self.get_parameter("state_interfaces").value)
            self._apply(config_from_node(self, PREFIXES))
        except (ConfigError, ValueError) as exc:
            return refuse(self, exc)
        self._pending = None
        self.interface = interface
        steps.warm_up()                         # compile or load the step before joining the graph
        tap = self._tap
        self.internals_pub = self.create_publisher(Float64MultiArray, "~/controller_state", qos(CONTROLLER_STATE))
        self.reference_pub = self.create_publisher(Float64MultiArray, "~/reference", qos(REFERENCE))
        self.gains_pub = self.create_publisher(Float64MultiArray, "~/gains", qos(GAINS))
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        if interface == "has_control":
            self.command_pub = self.create_publisher(JointState, COMMAND, CONTROL_QOS)
            sub = self.create_subscription(JointState, STATE, self._on_state, CONTROL_QOS, raw=True)
        else:
            self._mapping, self._names, self._index = mapping, None, None
            self.command_pub = self.create_publisher(
                Float64MultiArray, self.get_parameter("command_topic").value, CONTROL_QOS)
            sub = self.create_subscription(JointState, self.get_parameter("joint_states_topic").value,
                                           self._on_joint_state, CONTROL_QOS)
        self._state_topic = sub.topic_name
        self._publish_command = raw_publish(self.command_pub, tap)
        self._publish_internals = raw_publish(self.internals_pub, tap)
        self._publish_reference = raw_publish(self.reference_pub, tap)
        self._publish_gains = raw_publish(self.gains_pub, tap)
        self.publish_internals = bool(self.get_parameter("publish_internals").value)
        timer = self.create_timer(1.0, self._diagnose)
        self._entities = [sub, timer, self.command_pub, self.internals_pub, self.reference_pub, self.gains_pub,
                          self.diagnostics_pub]
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A new run from â(0); answer every state from now on."""
        self.reset()
        self.active = True
        where = f"states on {self._state_topic}, commands on {self.command_pub.topic_name}"
        if not self.quiet:
            self.get_logger().info(f"ready: answering {where} (interface {self.interface}, gains {self.k})")
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop answering; centre the valve (u = 0 for the next sample)."""
        self.active = False
        self._centre_valve()
        if not self.quiet:
            self.get_logger().info("inactive: valve centred, not answering")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.active:
            self.active = False
            self._centre_valve()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        """Destroy the topics and the timer made by ``configure``; forget the tables."""
        if self._entities:
            sub, timer, *pubs = self._entities
            self.destroy_subscription(sub)
            self.destroy_timer(timer)
            for pub in pubs:
                self.destroy_publisher(pub)
        self._entities = []
        self.cfg = None

    def _centre_valve(self) -> None:
        """A centred valve (u = 0): in ros2_control mode ``[0.0]`` on the command
        topic; else a command u = 0 for the sample after the last one answered."""
        if self.cfg is None:
            return
        if self.interface == "ros2_control":
            self.command_pub.publish(FORWARD_COMMAND_LAYOUT.encode([0.0]))
        elif self._last_state:
            self.command_pub.publish(COMMAND_LAYOUT.encode([0.0], stamp_ns=(self._sample(self._last_state) + 1)
                                                           * self.step_ns))

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
        self.step_ns = cfg.episode.step_ns

    def reset(self) -> None:
        """Estimates back to â(0); the next sample starts a new run."""
        if self.cfg is not None:
            self._mem[steps.A1_HAT], self._mem[steps.A2_HAT] = self.cfg.adaptation.initial
        self._mem[steps.X3D_PREV] = self._mem[steps.HAS_PREV] = 0.0
        self._last_state = self._last_command = b""
        self._next = 0                          # ros2_control: the sample the next state is
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
        with self._pending_lock:
            self._generation += 1
            generation = self._generation
            self._pending = None
        if cfg.reference.kind == "road" and not road_cached(cfg.reference, cfg.episode):
            # a tabulated road takes O(n log n) (0.07 s for 10 s at 1.6 kHz cutoff): built off the executor,
            # applied at the first sample after it is ready; the old reference runs meanwhile
            threading.Thread(target=self._build, args=(cfg, generation), name="controller-road", daemon=True).start()
        else:
            self._build(cfg, generation)
        return SetParametersResult(successful=True)

    def _build(self, cfg, generation: int) -> None:
        """The arrays of an accepted parameter set, pending for the next sample unless a newer set came."""
        try:
            arrays = EpisodeArrays.from_config(cfg)
        except (MemoryError, ConfigError) as exc:
            self.get_logger().error(f"cannot build the reference of the accepted parameters: {exc}")
            return
        with self._pending_lock:
            if generation == self._generation:
                self._pending = (cfg, arrays)

    # --- control loop: read -> update -> write --------------------------------
    def _sample(self, data: bytes) -> int:
        """Sample index of a serialized state's stamp."""
        return int(get_stamp(data)) // self.step_ns if len(data) >= 12 else -1

    def _on_state(self, data) -> None:
        if not self.active:
            return
        began = time.perf_counter_ns()
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
            with self._pending_lock:
                pending, self._pending = self._pending, None
            self._apply(*pending)
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
        self._answered(i, began)

    def _answered(self, i: int, began: int) -> None:
        """The internals of sample i after its command; count it (late: over one step)."""
        if self.publish_internals:
            self._publish_internals(bytes(self._internals))
            self._publish_reference(bytes(self._reference))
        self.states_answered += 1
        if time.perf_counter_ns() - began > self.step_ns:
            self.late += 1

    def _on_joint_state(self, msg: JointState) -> None:
        """ros2_control: a JointState by the mapping ``state_interfaces``, answered
        as the next sample with ``[u]`` on the command topic."""
        if not self.active:
            return
        began = time.perf_counter_ns()
        if msg.name != self._names:             # the joints' order is looked up once per layout
            self._names = list(msg.name)
            self._index = resolve(self._names, self._mapping)
        x = self._x
        arrays = (msg.position, msg.velocity, msg.effort)
        for k, (j, kind) in enumerate(self._index):
            values = arrays[kind]
            if j < 0 or j >= len(values):
                return self._refused("a joint or interface of state_interfaces missing")
            x[k] = values[j]
        if not (math.isfinite(x[0]) and math.isfinite(x[1]) and math.isfinite(x[2]) and math.isfinite(x[3])):
            return self._refused("a non-finite value")
        if self._pending is not None:
            with self._pending_lock:
                pending, self._pending = self._pending, None
            self._apply(*pending)
            self._announce = True
        i = self._next
        steps.encode_state(x, self.ap, i, self.step_ns, self._state_buf, self._clock_buf, self._scratch)
        steps.controller_sample(self._state_buf, self._mem, self._gains, self.ap, self.cp, self.rp, self.sp,
                                self.seed, self.dt, self.step_ns, self._command, self._internals,
                                self._reference, self.trace)
        self._next = i + 1
        if self._announce:
            self._publish_gains(GAINS_LAYOUT.encode([i * self.dt, *self.k]))
            self._announce = False
        _, u = steps.command_of(self._command, self.step_ns, self._scratch)
        self._publish_command(FORWARD_COMMAND_LAYOUT.encode([u]))
        self._answered(i, began)

    def _refused(self, what: str) -> None:
        self.malformed_states += 1
        self.get_logger().warning(f"refused a state ({what}); {self.malformed_states} so far",
                                  throttle_duration_sec=5.0)

    # --- diagnostics -----------------------------------------------------------
    def _diagnose(self) -> None:
        """/diagnostics: "<node>: control law" with the counts and the estimates' bounds
        (and, in a controller process with the collector off, the young generations' cycles)."""
        if not gc.isenabled():
            gc.collect(1)
        cp = self.cfg.adaptation
        a = (self.a1_hat, self.a2_hat)
        in_bounds = all(lo <= v <= hi for v, lo, hi in zip(a, cp.lower, cp.upper))
        values = {"lifecycle": state_label(self), "states_answered": self.states_answered, "late": self.late,
                  "malformed_states": self.malformed_states, "conflicts": self.conflicts,
                  "a1_hat": f"{a[0]:.6g}", "a2_hat": f"{a[1]:.6g}", "estimates_in_bounds": in_bounds}
        ok = in_bounds and not self.conflicts
        status = DiagnosticStatus(
            level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
            name=f"{self.get_fully_qualified_name()}: control law",
            message=(f"{state_label(self)}, {self.states_answered} answered, {self.late} late, "
                     f"{self.malformed_states} malformed" + ("" if in_bounds else ", estimates out of bounds")),
            hardware_id="has_control controller",
            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(msg)


def main(args=None):
    node_main(args, ControllerNode, _serve)


def _serve(executor, node: ControllerNode) -> None:
    """A controller process: no collector pause between a state and its answer
    (the once-a-second diagnostics collect instead), then serve until shutdown."""
    gc.disable()
    spin(executor)
