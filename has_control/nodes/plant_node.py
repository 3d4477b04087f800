"""The plant node: simulates the actuator at one 0.3 ms step per sample.

A thin shell over :class:`has_control.loop.plant.PlantProcess` (the state,
the step, the guards) and :func:`has_control.loop.schedule.run_loop` (both
timing policies): this module declares the parameters, makes the topics and
hands each command's bytes to the process. Every step is one compiled call
(:func:`has_control.wire.steps.plant_sample`) of the one implementation,
:func:`has_control.core.actuator.plant_step`, that also encodes the new state;
commands are taken as serialized bytes and decoded by compiled code
(:func:`has_control.wire.steps.command_of`). So a run through the graph equals the in-process trace, bit for bit.

``mode: lockstep`` (default): publish state i, wait for command i, advance,
publish state i + 1 — as fast as the controller answers. If no command
arrives within ``command_timeout`` seconds of wall time, the fail-safe
applies u = 0 (valve centred) to that sample, warns once per outage and
counts it; control resumes when commands return. The first sample of a run
waits up to ``startup_timeout`` instead when a controller is matched (one
that has just been discovered may not yet have discovered us). A state unanswered after a
quarter of the timeout is sent again each quarter (a controller that has
just matched may have missed it; a repeated state is answered with the
same command).

``mode: realtime``: paced lock-step (:class:`has_control.loop.schedule.Paced`):
sample i is due at t0 + i·Δt of wall time; a command that misses its sample's
deadline is a counted miss (the last command is held), and after
``failsafe_samples`` consecutive misses the valve is centred. The loop runs
on the thread that owns the executor (``main``, or ``has-control stack
--realtime``), with SCHED_FIFO at ``realtime_priority`` where permitted.

Both modes: a diverged state (|y| > y_limit or not finite) is published and
ends the episode. Two different commands for one sample (a second
controller on the topic) are counted as ``conflicts`` and logged as errors.
A command of another layout, a stale stamp or a non-finite
value is refused and counted (``malformed_commands``, logged at most every
5 s); it never reaches the state. ``/diagnostics`` gets the loop's figures
once a second (rate, fail-safe samples, refused commands; in realtime also
real-time factor, misses and lateness percentiles).

Topics: ``state`` (sensor_msgs/JointState, out; with ``noise.added_by: plant``
the sensors' readings, true state plus the seeded noise ``noise.*`` of the
sample, and ``true_state`` beside it), ``command``
(sensor_msgs/JointState, in), ``clock`` (rosgraph_msgs/Clock, out; resolves to
``/clock`` in the root namespace). Services (std_srvs/Trigger): ``~/reset``
back to the initial state at sample 0 and idle; ``~/start`` run an episode of
``samples`` samples (0: until stopped) from the current state.
Parameters: ``actuator.*``, ``simulation.*``, ``noise.*`` (read only with
``noise.added_by: plant``), ``plant.*`` (this plant where it
differs from the model ``actuator.*``: mass, bulk_modulus, damping, leakage,
supply_pressure, valve_gain, each defaulting to its ``actuator.*``; the valve's
travel limit ``valve_limit`` [m] and lag ``valve_time_constant`` [s]), ``mode``, ``samples``,
``command_timeout`` [s], ``startup_timeout`` [s], ``failsafe_samples``, ``realtime_priority``
(SCHED_FIFO priority, 0: normal scheduling), ``autostart`` (configure and
activate at start-up; false: wait unconfigured for lifecycle transitions),
``keep_alive`` (a served plant: episodes only on ``~/start``, and ``main``
keeps serving after an episode instead of exiting), ``foxglove_port``
(serve ``state`` and ``clock`` live on a Foxglove WebSocket at this port of
127.0.0.1, :mod:`has_control.nodes.foxglove`; 0: off).

``interface: ros2_control`` (read at start-up): the plant speaks as a
ros2_control system does (``topic_based_ros2_control``, a hardware driver with
joint_state_broadcaster and a forward_command_controller): its state, the same
``sensor_msgs/JointState`` (joints actuator, chamber_1, chamber_2: the default
``state_interfaces`` of :mod:`has_control.wire.joint_mapping`), stamped with the
simulation time i·Δt, on ``joint_states_topic`` (default ``/joint_states``), and
the valve command ``std_msgs/Float64MultiArray`` ``[u]`` from ``command_topic``
(default ``/forward_command_controller/commands``). The command has no stamp:
it answers the latest state published (:mod:`has_control.loop.plant`), so the
controller's ros2_control mode runs end to end, lock-step or paced, against
this plant. ``drop_states`` (a test hook, N ≥ 2; 0: off): the state of every
Nth sample is not published; lock-step runs that sample at once with the last
command held (counted as ``dropped_states`` in /diagnostics). A command delay is
``plant.delay`` [samples].

Managed node (:mod:`has_control.nodes.managed`): ``configure`` validates the
parameters, builds the plant's tables and creates the topics; ``activate``
lets the loop run (``main`` starts an episode when a controller connects,
unless ``keep_alive``; ``~/start`` is served); ``deactivate`` ends the
episode with the valve centred; ``cleanup`` and ``shutdown`` release the topics.
"""
from __future__ import annotations

import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from has_control.common.errors import ConfigError
from has_control.config.table import Param, refusal, table
from has_control.loop.plant import PlantProcess
from has_control.loop.report import LoopReports, Report, run_reported
from has_control.loop.schedule import MODES, LoopStats, schedule_of
from has_control.wire import steps
from has_control.wire.topics import CLOCK_TOPIC, COMMAND, COMMAND_NAMES, STATE, TRUE_STATE
from has_control.nodes.live_tap import node_tap
from has_control.nodes.managed import AUTOSTART, autostart, refuse, state_label
from has_control.nodes.runtime import (CONTROL_OFFERED_QOS, CONTROL_QOS, node_main,
                                       publish_diagnostics, qos, raw_publish,
                                       trigger_service)
from has_control.nodes.parameters import (check_changes, config_from_node, declare_config, declare_plant_overrides,
                                          declare_table, interface_parameters)

PREFIXES = ("actuator.", "simulation.", "plant.", "noise.")
#: The plant's own parameters (its table; the model's are :data:`~has_control.config.schema.CONFIG_TABLE`'s).
OWN_PARAMETERS = table((
    Param("mode", "str", "lockstep", text="lockstep (as fast as the controller answers) | realtime (paced to "
          "wall time)", choices=MODES, read_only=True),
    Param("command_timeout", "double", 0.5, "s of wall time", "lock-step: wait this long for a command before "
          "the fail-safe", lower=0.0, lower_open=True),
    Param("startup_timeout", "double", 5.0, "s", "the first answer of a run, while a matched controller has not "
          "answered", lower=0.0, lower_open=True),
    Param("failsafe_samples", "int", 10, "samples", "realtime: misses in a row before the valve is centred",
          lower=0),
    Param("realtime_priority", "int", 50, "", "realtime: SCHED_FIFO priority of the loop (0: normal scheduling)",
          lower=0, upper=99, read_only=True),
    Param("samples", "int", 0, "samples", "samples per episode (0: until stopped)", lower=0),
    AUTOSTART,
    Param("keep_alive", "bool", False, text="a served plant: episodes only on ~/start, kept serving after each",
          read_only=True),
    *interface_parameters("plant"),
    Param("drop_states", "int", 0, "samples", "test hook: the state of every Nth sample is not published "
          "(0: none; else >= 2)", lower=0, check_more=lambda n: "must be 0 (none) or >= 2" if n == 1 else None),
))
#: Parameters that change a running plant: where each lives in the process.
LIVE = {"samples": "samples", "command_timeout": "schedule.timeout", "startup_timeout": "schedule.startup_timeout",
        "failsafe_samples": "schedule.failsafe_samples", "drop_states": "drop_every"}


class _Of:
    """A node attribute that is the process's ``path`` (e.g. ``fail_safe.samples``)."""

    def __init__(self, path: str):
        *self.head, self.last = path.split(".")

    def _owner(self, node):
        obj = node.process
        for name in self.head:
            obj = getattr(obj, name)
        return obj

    def __get__(self, node, cls=None):
        return self if node is None else getattr(self._owner(node), self.last)

    def __set__(self, node, value) -> None:
        setattr(self._owner(node), self.last, value)


def _other_layout(data: bytes) -> tuple[int, float] | None:
    """The slow path: (stamp [ns], u [m]) of a JointState of another layout, by name; None if not one."""
    try:
        from rclpy.serialization import deserialize_message
        msg = deserialize_message(data, JointState)
        u = float(msg.position[list(msg.name).index(COMMAND_NAMES[0])])
        return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec, u
    except Exception:                        # noqa: BLE001 - any undecodable bytes
        return None


def _other_forward(data: bytes) -> tuple[int, float] | None:
    """The slow path: (−1, u [m]) of a Float64MultiArray ``[u]`` of another layout; None if not one."""
    try:
        from rclpy.serialization import deserialize_message   # the rare message only
        msg = deserialize_message(data, Float64MultiArray)
        return (-1, float(msg.data[0])) if len(msg.data) == 1 else None
    except Exception:                        # noqa: BLE001 - any undecodable bytes
        return None


#: The plant's figures and settings as node attributes: where each lives in the process.
PROCESS_ATTRIBUTES = {
    **{n: n for n in ("x", "sample", "finished", "diverged", "command_sample", "command_u", "samples",
                      "malformed_commands", "publish_failures", "actuator", "ap", "step_s", "step_ns", "run_seconds")},
    "failsafe_events": "fail_safe.samples", "_in_outage": "fail_safe.in_outage", "conflicts": "conflicts.count",
    "stop_on_conflict": "conflicts.stop", "timeout": "schedule.timeout",
    "startup_timeout": "schedule.startup_timeout", "failsafe_samples": "schedule.failsafe_samples"}


class PlantNode(LifecycleNode):
    """The plant as a managed node: its parameters, topics and reports over a
    :class:`~has_control.loop.plant.PlantProcess` (see the module docstring)."""

    def __init__(self, name: str = "plant", tap=None, **kwargs):
        """``tap(topic)``: a function taking every state and clock message published (an in-process observer)."""
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES, read_only=PREFIXES)
        declare_plant_overrides(self)
        declare_table(self, OWN_PARAMETERS.values())
        self.configure_error = ""
        self.quiet = False                        # True: no "ready"/"inactive" lines (stack drives us)
        self.active = self.configured = False
        self.process: PlantProcess | None = None
        self._entities: list = []
        self.run_requested = False                # start() asks the executor's owner to run the loop
        self._tap, self.live_view = node_tap(self, tap)      # parameter foxglove_port
        trigger_service(self, "~/reset", self._reset_state, "plant at the initial state, sample 0, idle")
        trigger_service(self, "~/start", self.start, "episode started")
        self.add_on_set_parameters_callback(self._on_set_parameters)
        if self.get_parameter("autostart").value:
            autostart(self)

    # --- lifecycle -----------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Validate the parameters, build the plant's tables, create the topics."""
        try:
            value, cfg = _own_values(self), config_from_node(self, PREFIXES)
        except (ConfigError, ValueError) as exc:
            return refuse(self, exc)
        self.mode, self.priority = value["mode"], int(value["realtime_priority"])
        schedule = schedule_of(self.mode, timeout=float(value["command_timeout"]),
                               startup_timeout=float(value["startup_timeout"]),
                               failsafe_samples=int(value["failsafe_samples"]))
        steps.warm_up()                                # compile or load the step and decoder first
        tap = self._tap
        self.interface = value["interface"]
        ros2_control = self.interface == "ros2_control"      # a hardware driver's topics (docs/ros2_control.md)
        self.state_pub = self.create_publisher(JointState, value["joint_states_topic"] if ros2_control else STATE,
                                               CONTROL_OFFERED_QOS)
        self.clock_pub = self.create_publisher(Clock, CLOCK_TOPIC, qos(CLOCK_TOPIC))
        self._publish_state = raw_publish(self.state_pub, tap)
        self._publish_clock = raw_publish(self.clock_pub, tap)
        pubs = [self.state_pub, self.clock_pub]
        if cfg.noise.added_by == "plant":
            pubs.append(self.create_publisher(JointState, TRUE_STATE, CONTROL_OFFERED_QOS))
            self._publish_true = raw_publish(pubs[-1], tap)
        self.process = PlantProcess(cfg, schedule, self, self.get_logger(), samples=int(value["samples"]),
                                    fallback=_other_forward if ros2_control else _other_layout,
                                    drop_every=int(value["drop_states"]))
        if ros2_control:
            self._command_sub = self.create_subscription(Float64MultiArray, value["command_topic"],
                                                         self._on_forward_command, CONTROL_QOS, raw=True)
        else:
            self._command_sub = self.create_subscription(JointState, COMMAND, self._on_command, CONTROL_QOS,
                                                         raw=True)
        self._command_topic = self._command_sub.topic_name
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.configured = True
        timers, self.reports = [], LoopReports(self.process)
        if not schedule.paced:                   # the watchdog and the once-a-second report
            timers = [self.create_timer(max(schedule.timeout / 4, 0.01), self._check_deadline),
                      self.create_timer(1.0, self._report_lockstep)]
        self._entities = [self._command_sub, timers, *pubs, self.diagnostics_pub]
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = True
        if not self.quiet:
            self.get_logger().info(
                f"ready: {self.mode} plant, states on {self.state_pub.topic_name}, "
                f"commands from {self._command_topic}, step {self.step_s * 1e3:g} ms")
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """End the episode with the valve centred; take no commands."""
        self._stop()
        if not self.quiet:
            self.get_logger().info(f"inactive: episode ended at sample {self.sample}, valve centred")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _stop(self) -> None:
        self.active = False
        if self.configured:
            self.process.stop()
            self.run_requested = False

    def _release(self) -> None:
        """Destroy the topics and timers made by ``configure``."""
        if self._entities:
            sub, timers, *pubs = self._entities
            self.destroy_subscription(sub)
            for t in timers:
                self.destroy_timer(t)
            for pub in pubs:
                self.destroy_publisher(pub)
        self._entities = []
        self.configured = False

    def _on_set_parameters(self, params) -> SetParametersResult:
        reason = check_changes(OWN_PARAMETERS, params)
        if reason is not None:
            return SetParametersResult(successful=False, reason=reason)
        if self.process is not None:
            for p in params:
                if p.name in LIVE:
                    _Of(LIVE[p.name]).__set__(self, p.value)
        return SetParametersResult(successful=True)

    # --- the process's port: state out, command in -----------------------------
    def _reset_state(self) -> None:
        """Back to the initial state at sample 0, idle until :meth:`start`."""
        if self.configured:
            self.process.reset()

    def start(self) -> str | None:
        """Run an episode from the current state (lock-step: publishes it now); only when active
        (else the reason, which ``~/start`` answers with success false).
        The executor's owner then runs :meth:`run` (``main``, ``stack``) or just spins."""
        if not self.active:
            reason = f"refused: the plant is {state_label(self)}, not active"
            self.get_logger().warning(f"~/start {reason}")
            return reason
        self.process.start()
        self.run_requested = True

    def connected(self) -> bool:
        """Both directions of the loop have matched a peer (a controller is listening and talking)."""
        return bool(self.state_pub.get_subscription_count() and self._command_sub.get_publisher_count())

    def command_publishers(self) -> str:
        return f"{self.count_publishers(self._command_topic)} publishers on {self._command_topic}"

    def publish(self, state: bytes, true_state: bytes | None, clock: bytes) -> bool:
        """Write: the state (the controller waits on it), the true state, the clock; False if DDS refused."""
        try:
            self._publish_state(state)
            if true_state is not None:
                self._publish_true(true_state)
            self._publish_clock(clock)
            return True
        except _rclpy.RCLError:                  # a reader gone, a full history: the sample goes unanswered
            return False

    def resend(self, state: bytes) -> None:
        self.state_pub.publish(state)             # not to observers

    def _on_command(self, data: bytes) -> None:
        if self.active:
            self.process.on_command(data)

    def _on_forward_command(self, data: bytes) -> None:
        if self.active:
            self.process.on_forward_command(data)

    def _check_deadline(self) -> None:
        self.process.schedule.tick(self.process, time.monotonic())

    # --- the loop and its reports ------------------------------------------------
    def run(self, executor, on_second=None, check=None) -> LoopStats:
        """Run the requested episode on this thread, which must own ``executor``, with its
        reports (:func:`~has_control.loop.report.run_reported`; realtime: paced, SCHED_FIFO where permitted)."""
        self.run_requested = False
        return run_reported(self.process, executor.spin_once, self.reports, self._publish_report,
                            priority=self.priority, on_second=on_second, check=check)

    run_realtime = run

    realtime_stats = property(lambda self: self.reports.realtime_stats)

    def _report_lockstep(self) -> None:
        self._publish_report(self.reports.lockstep())

    def _publish_report(self, report: Report) -> None:
        publish_diagnostics(self, self.diagnostics_pub, report.what, "has_control plant", report.values, report.ok,
                            report.message)


for _name, _path in PROCESS_ATTRIBUTES.items():
    setattr(PlantNode, _name, _Of(_path))


def _own_values(node: PlantNode) -> dict:
    """The plant's own parameters by name; ValueError naming the first out of range."""
    value = {name: node.get_parameter(name).value for name in OWN_PARAMETERS}
    for name in OWN_PARAMETERS:
        reason = refusal(OWN_PARAMETERS, name, value[name])
        if reason is not None:
            raise ValueError(f"parameter {reason}")
    return value


def main(args=None):
    node_main(args, PlantNode, _serve)


def _serve(executor, node: PlantNode) -> None:
    """Once active, start an episode when a controller connects (unless
    ``keep_alive``: episodes on ``~/start`` only); run until it ends (or, with
    ``keep_alive``, until shutdown)."""
    keep_alive = bool(node.get_parameter("keep_alive").value)
    if not node.active:
        node.get_logger().info(f"unconfigured: waiting for lifecycle transitions (ros2 lifecycle set "
                               f"{node.get_fully_qualified_name()} configure, then activate)")
    elif keep_alive:
        node.get_logger().info("waiting for ~/start")
    started = False
    while rclpy.ok():
        if not (keep_alive or started) and node.active and node.connected():
            node.get_logger().info("controller connected: starting the run")
            node.start()
            started = True
        if node.run_requested:
            node.run(executor)
        else:
            executor.spin_once(timeout_sec=0.05)
        if node.configured and node.finished and node.run_seconds:
            _log_finished(node)
            node.run_seconds = 0.0
        if started and node.finished and not keep_alive:
            break


def _log_finished(node: PlantNode) -> None:
    rate = node.sample / node.run_seconds if node.run_seconds else float("nan")
    node.get_logger().info(
        f"finished {node.sample} samples at t = {node.sample * node.step_s:.4f} s: "
        f"y = {node.x[0]:.9e} m, fail-safe events = {node.failsafe_events}, {rate:.0f} samples/s"
        + (" (diverged)" if node.diverged else ""))
