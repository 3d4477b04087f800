"""The controller node: the adaptive back-stepping law on every state it receives.

A thin shell over :class:`has_control.loop.controller.ControllerProcess` (the
law, its estimates, pending parameter swaps) and one of the two ports of
:mod:`has_control.loop.ports`, chosen at configure by ``interface``. Each state
arrives as serialized bytes; one compiled call
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
takes). Each state that arrives is answered at once, as the sample its header
stamp names (from the first state's, rounded to the grid; missing and stale
states counted in /diagnostics); see docs/ros2_control.md.

``/diagnostics`` (once a second, name "<node>: control law"): states
answered, late (answers that took longer than one step Δt to compute),
malformed, conflicts and whether â1, â2 are within ``adaptation.lower..upper``.
"""

import gc

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from has_control.common.errors import ConfigError
from has_control.config.table import Param, refusal, table
from has_control.loop.controller import ControllerProcess
from has_control.loop.guards import Conflicts
from has_control.loop.ports import Outputs, make_port
from has_control.wire import steps
from has_control.wire.topics import CONTROLLER_STATE, GAINS, REFERENCE
from has_control.wire.joint_mapping import DEFAULT_STATE_INTERFACES, parse_state_interfaces
from has_control.nodes.live_tap import node_tap
from has_control.nodes.managed import AUTOSTART, autostart as bring_up_now, refuse, state_label
from has_control.nodes.runtime import (CONTROL_OFFERED_QOS, CONTROL_QOS, node_main, publish_diagnostics, qos,
                                       raw_publish, spin,
                                       trigger_service)
from has_control.nodes.parameters import (check_changes, config_from_node, declare_config, declare_table,
                                          interface_parameters)

PREFIXES = ("actuator.", "simulation.", "gains.", "adaptation.", "reference.", "noise.")
#: The controller's own parameters (its table; the law's are :data:`~has_control.config.schema.CONFIG_TABLE`'s).
OWN_PARAMETERS = table((
    Param("publish_internals", "bool", True, text="publish ~/controller_state and ~/reference every sample"),
    *interface_parameters("controller"),
    Param("state_interfaces", "str[]", list(DEFAULT_STATE_INTERFACES), length=4, read_only=True,
          text="ros2_control: joint/interface of y [m], y_dot [m/s], P1 [Pa], P2 [Pa] "
          "(interface: position, velocity or effort)"),
    AUTOSTART,
))
_COMMAND_TYPES = {"JointState": JointState, "Float64MultiArray": Float64MultiArray}


class ControllerNode(LifecycleNode):
    def __init__(self, name: str = "controller", tap=None, **kwargs):
        """``tap(topic)``: a function taking every message published on ``topic`` (an in-process observer)."""
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES, read_only=("simulation.",))
        declare_table(self, OWN_PARAMETERS.values())
        autostart = bool(self.get_parameter("autostart").value)
        self.process: ControllerProcess | None = None
        self.port = None
        self.conflicts_guard = Conflicts(self.get_logger(), self._state_publishers, "conflicting states")
        self.configure_error = ""
        self.quiet = False                        # True: no "ready"/"inactive" lines (stack drives us)
        self.active = False
        self._entities: list = []
        self._state_topic = ""
        self._trace_samples = 0
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._tap, self.live_view = node_tap(self, tap)      # parameter foxglove_port
        trigger_service(self, "~/reset", self.reset, "estimates at a(0), next state starts a new run")
        if autostart:
            bring_up_now(self)

    # --- what the process holds ------------------------------------------------
    cfg = property(lambda self: self.process.cfg if self.process is not None else None)
    k = property(lambda self: self.process.k)
    dt = property(lambda self: self.process.dt)
    step_ns = property(lambda self: self.process.step_ns)
    trace = property(lambda self: self.process.trace)
    _pending = property(lambda self: self.process.pending)
    malformed_states = property(lambda self: self.process.malformed_states)
    states_answered = property(lambda self: self.process.states_answered)
    late = property(lambda self: self.process.late)
    conflicts = property(lambda self: self.conflicts_guard.count)
    a2_hat = property(lambda self: self.process.a2_hat)

    @property
    def a1_hat(self) -> float:
        return self.process.a1_hat

    @a1_hat.setter
    def a1_hat(self, value: float) -> None:
        self.process.mem[steps.A1_HAT] = value

    def record_trace(self, samples: int):
        """Keep rows 0..samples-1 of the run (TRACE_COLUMNS) in a preallocated array."""
        return self.process.record_trace(samples)

    # --- lifecycle -----------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Validate the parameters, build the tables and the port, create the topics."""
        param = {key: self.get_parameter(key).value for key in OWN_PARAMETERS}
        try:
            for key in ("interface", "joint_states_topic", "command_topic"):
                reason = refusal(OWN_PARAMETERS, key, param[key])
                if reason is not None:
                    raise ValueError(f"parameter {reason}")
            mapping = parse_state_interfaces(param["state_interfaces"])
            cfg = config_from_node(self, PREFIXES)
            process = ControllerProcess(cfg, self.get_logger())
        except (ConfigError, ValueError) as exc:
            return refuse(self, exc)
        if self.process is not None:
            process.trace = self.process.trace
        self.process, self.interface = process, param["interface"]
        steps.warm_up()                         # compile or load the step before joining the graph
        tap = self._tap
        self.internals_pub = self.create_publisher(Float64MultiArray, "~/controller_state", qos(CONTROLLER_STATE))
        self.reference_pub = self.create_publisher(Float64MultiArray, "~/reference", qos(REFERENCE))
        self.gains_pub = self.create_publisher(Float64MultiArray, "~/gains", qos(GAINS))
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        out = Outputs(None, None, raw_publish(self.internals_pub, tap), raw_publish(self.reference_pub, tap),
                      raw_publish(self.gains_pub, tap), bool(param["publish_internals"]),
                      tap(self.internals_pub.topic_name) if tap is not None else None)   # unpublished: to observers
        self.port = port = make_port(self.interface, process, out, self.conflicts_guard, mapping=mapping,
                                     state_topic=param["joint_states_topic"], command_topic=param["command_topic"],
                                     serialize=serialize_message)
        self.command_pub = self.create_publisher(_COMMAND_TYPES[port.command_type], port.command_topic,
                                                 CONTROL_OFFERED_QOS)
        out.command, out.command_again = raw_publish(self.command_pub, tap), self.command_pub.publish
        sub = self.create_subscription(JointState, port.state_topic, self._on_state, CONTROL_QOS, raw=port.raw)
        self._state_topic = sub.topic_name
        self.publish_internals, self._outputs = out.publish_internals, out
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
        self.port.centre()
        if not self.quiet:
            self.get_logger().info("inactive: valve centred, not answering")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.active:
            self.active = False
            self.port.centre()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        """Destroy the topics and the timer made by ``configure``."""
        if self._entities:
            sub, timer, *pubs = self._entities
            self.destroy_subscription(sub)
            self.destroy_timer(timer)
            for pub in pubs:
                self.destroy_publisher(pub)
        self._entities = []

    def reset(self) -> None:
        """Estimates back to â(0); the next sample starts a new run."""
        if self.process is not None:
            self.process.reset()
            self.port.reset()

    # --- parameters --------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        """Checked by the tables and the core; the old values stay on a refusal. Accepted:
        the law's parameters from the next sample (pending), ``publish_internals`` too."""
        reason = check_changes(OWN_PARAMETERS, params)
        if reason is not None:
            return SetParametersResult(successful=False, reason=reason)
        changes = {p.name: p.value for p in params if p.name.startswith(PREFIXES)}
        if changes and self.process is not None:
            try:
                cfg = config_from_node(self, PREFIXES, overrides=changes)
            except ConfigError as exc:
                reason = str(exc)
                self.get_logger().warning(f"rejected {sorted(changes)}: {reason}")
                return SetParametersResult(successful=False, reason=reason)
            self.process.propose(cfg)               # pending: applied at the next sample
        for p in params:
            if p.name == "publish_internals" and self.process is not None:
                self.publish_internals = self._outputs.publish_internals = bool(p.value)
        return SetParametersResult(successful=True)

    # --- control loop: read -> update -> write (the port) -------------------------
    def _on_state(self, data) -> None:
        if self.active:
            self.port.on_state(data)

    _on_joint_state = _on_state

    def _state_publishers(self) -> str:
        return f"{self.count_publishers(self._state_topic)} publishers on {self._state_topic}"

    # --- diagnostics -----------------------------------------------------------
    def _diagnose(self) -> None:
        """/diagnostics: "<node>: control law" (:meth:`ControllerProcess.diagnosis`: the counts and
        the estimates' bounds; and, in a controller process with the collector off, the young generations' cycles)."""
        if not gc.isenabled():
            gc.collect(1)
        values, ok, message = self.process.diagnosis(state_label(self), self.conflicts, self.port)
        publish_diagnostics(self, self.diagnostics_pub, "control law", "has_control controller", values, ok, message)


def main(args=None):
    node_main(args, ControllerNode, _serve)


def _serve(executor, node: ControllerNode) -> None:
    """A controller process: no collector pause between a state and its answer
    (the once-a-second diagnostics collect instead), then serve until shutdown.
    An unconfigured controller (``autostart: false``) says what it waits for."""
    if not node.active:
        node.get_logger().info(f"unconfigured: waiting for lifecycle transitions (ros2 lifecycle set "
                               f"{node.get_fully_qualified_name()} configure, then activate)")
    gc.disable()
    spin(executor)
