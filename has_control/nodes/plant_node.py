"""The plant node: simulates the actuator at one 0.3 ms step per sample.

Every step is one compiled call (:func:`has_control.wire.steps.plant_sample`) of
the one implementation, :func:`has_control.core.actuator.plant_step`, that also
encodes the new state; commands are taken as serialized bytes and decoded by
compiled code (:func:`has_control.wire.steps.command_of`). So a run through the
graph equals the in-process trace, bit for bit.

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

``mode: realtime``: paced lock-step (:mod:`has_control.nodes.pacing`):
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

Managed node (:mod:`has_control.nodes.managed`): ``configure`` validates the
parameters, builds the plant's tables and creates the topics; ``activate``
lets the loop run (``main`` starts an episode when a controller connects,
unless ``keep_alive``; ``~/start`` is served); ``deactivate`` ends the
episode with the valve centred; ``cleanup`` and ``shutdown`` release the topics.
"""
from __future__ import annotations

import math
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from has_control.wire import steps
from has_control.wire.topics import (CLOCK_LAYOUT, CLOCK_TOPIC, COMMAND, COMMAND_NAMES, STATE, STATE_LAYOUT,
                                     TRUE_STATE)
from has_control.wire.codec import NOT_FINITE
from has_control.common.errors import ConfigError
from has_control.nodes.live_tap import node_tap
from has_control.nodes.managed import AUTOSTART, autostart, refuse, state_label
from has_control.nodes.runtime import CONTROL_QOS, node_main, qos, raw_publish, trigger_service
from has_control.nodes.pacing import LoopStats, run_paced
from has_control.nodes.parameters import config_from_node, declare_config, declare_plant_overrides

PREFIXES = ("actuator.", "simulation.", "plant.", "noise.")
MODES = ("lockstep", "realtime")
#: The plant's own parameters: (name, default, meaning and unit).
OWN_PARAMETERS = (
    ("mode", "lockstep", "lockstep (as fast as the controller answers) | realtime (paced to wall time)"),
    ("command_timeout", 0.5, "lock-step: wait this long for a command before the fail-safe [s of wall time]"),
    ("startup_timeout", 5.0, "the first answer of a run, while a matched controller has not answered [s]"),
    ("failsafe_samples", 10, "realtime: misses in a row before the valve is centred [samples]"),
    ("realtime_priority", 50, "realtime: SCHED_FIFO priority of the loop, 0..99 (0: normal scheduling)"),
    ("samples", 0, "samples per episode (0: until stopped)"),
    AUTOSTART,
    ("keep_alive", False, "a served plant: episodes only on ~/start, kept serving after each"),
)
#: Recent samples whose applied answer is kept, to catch a second controller's late answers.
ANSWERS_KEPT = 4096


class PlantNode(LifecycleNode):
    def __init__(self, name: str = "plant", tap=None, **kwargs):
        """``tap(topic)``: a function taking every state and clock message published (an in-process observer)."""
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES, read_only=PREFIXES)
        declare_plant_overrides(self)
        for name, value, text in OWN_PARAMETERS:
            self.declare_parameter(name, value, ParameterDescriptor(
                description=text, read_only=name in ("mode", "realtime_priority", "autostart"),
                additional_constraints=f"one of: {', '.join(MODES)}" if name == "mode" else ""))
        self.configure_error = ""
        self.quiet = False                        # True: no "ready"/"inactive" lines (stack drives us)
        self.active = self.configured = False
        self._entities: list = []
        self.failsafe_events = 0                  # samples run with the valve centred
        self.malformed_commands = 0
        self.publish_failures = 0                 # states DDS refused to send
        self.conflicts = 0                        # samples answered twice, differently
        self.stop_on_conflict = False             # end the episode at the first one (stack does)
        self.started_at = self.run_seconds = 0.0
        self.finished = True
        self._in_outage = False
        self.log: list[tuple[int, float, float, float, float, float]] | None = None
        self.realtime_stats: dict[str, float] = {}
        self.run_requested = False                # realtime: start() asks the executor's owner to run
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
            for name in ("mode", "command_timeout", "startup_timeout", "failsafe_samples", "realtime_priority",
                         "samples"):
                reason = self._invalid(name, self.get_parameter(name).value)
                if reason is not None:
                    raise ValueError(f"parameter {reason}")
            cfg = config_from_node(self, PREFIXES)
        except (ConfigError, ValueError) as exc:
            return refuse(self, exc)
        self.actuator = cfg.plant.actuator(cfg.actuator)      # this plant's own parameters
        self.ap = cfg.plant.as_array(cfg.actuator)            # ... and its valve
        self.step_s = cfg.episode.step
        self.step_ns = cfg.episode.step_ns
        self.y_limit = cfg.episode.y_limit
        self.samples = int(self.get_parameter("samples").value)
        self.timeout = float(self.get_parameter("command_timeout").value)
        self.startup_timeout = float(self.get_parameter("startup_timeout").value)
        self.failsafe_samples = int(self.get_parameter("failsafe_samples").value)
        self.priority = int(self.get_parameter("realtime_priority").value)
        self.mode = self.get_parameter("mode").value
        self._state_msg = STATE_LAYOUT.buffer()
        # noise.added_by plant: ``state`` carries the sensors' readings, ``true_state`` the state
        self.measured = cfg.noise.added_by == "plant"
        self.sp, self.seed = cfg.noise.as_array(cfg.episode.step), int(cfg.noise.seed)
        self._true_msg = STATE_LAYOUT.buffer()
        self._clock_msg = CLOCK_LAYOUT.buffer()
        self._scratch = steps.scratch()
        steps.warm_up()                                # compile or load the step and decoder first
        tap = self._tap
        self.state_pub = self.create_publisher(JointState, STATE, CONTROL_QOS)
        self.clock_pub = self.create_publisher(Clock, CLOCK_TOPIC, qos(CLOCK_TOPIC))
        self._publish_state = raw_publish(self.state_pub, tap)
        self._publish_clock = raw_publish(self.clock_pub, tap)
        if self.measured:
            self.true_state_pub = self.create_publisher(JointState, TRUE_STATE, CONTROL_QOS)
            self._publish_true = raw_publish(self.true_state_pub, tap)
        self._command_sub = self.create_subscription(JointState, COMMAND, self._on_command, CONTROL_QOS, raw=True)
        self._command_topic = self._command_sub.topic_name
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.configured = True
        self._reset_state()
        timers = []
        if self.mode == "lockstep":
            self._watchdog = self.create_timer(max(self.timeout / 4, 0.01), self._check_deadline)
            self._last_report = (time.monotonic(), 0)
            timers = [self._watchdog, self.create_timer(1.0, self._report_lockstep)]
        self._entities = [self._command_sub, timers, self.state_pub, self.clock_pub, self.diagnostics_pub]
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
            self.command_sample, self.command_u = self.sample, 0.0
            if not self.finished:
                self._finish()
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

    # --- parameters --------------------------------------------------------
    @staticmethod
    def _invalid(name: str, value) -> str | None:
        """Why ``value`` is not a valid ``name``, or None."""
        if name == "samples" and not (isinstance(value, int) and value >= 0):
            return f"samples = {value!r}: must be an integer >= 0"
        if name in ("command_timeout", "startup_timeout") and not (
                isinstance(value, float) and 0 < value < float("inf")):
            return f"{name} = {value!r}: must be a number > 0 [s]"
        if name == "failsafe_samples" and not (isinstance(value, int) and value >= 0):
            return f"failsafe_samples = {value!r}: must be an integer >= 0"
        if name == "realtime_priority" and not (isinstance(value, int) and 0 <= value <= 99):
            return f"realtime_priority = {value!r}: must be an integer in 0..99 (0: normal scheduling)"
        if name == "mode" and value not in MODES:
            return f"mode = {value!r}: expected one of {', '.join(MODES)}"
        return None

    def _on_set_parameters(self, params) -> SetParametersResult:
        for p in params:
            reason = self._invalid(p.name, p.value)
            if reason is None and p.name in ("mode", "realtime_priority"):
                reason = f"{p.name}: read at start-up only; restart the plant to change it"
            if reason is not None:
                return SetParametersResult(successful=False, reason=reason)
        for p in params:
            if p.name == "samples":
                self.samples = p.value
            elif p.name == "command_timeout":
                self.timeout = p.value
            elif p.name == "startup_timeout":
                self.startup_timeout = p.value
        return SetParametersResult(successful=True)

    # --- the hardware: state out, command in, step ----------------------------
    def _reset_state(self) -> None:
        """Back to the initial state at sample 0, idle until :meth:`start`."""
        if not self.configured:
            return
        self.x = self._initial_state()
        self.sample = self._first_sample = 0
        self.finished = False
        self.diverged = False
        self.command_sample, self.command_u = -1, 0.0
        self._answered_at, self._answers = [-1] * ANSWERS_KEPT, [0.0] * ANSWERS_KEPT
        steps.encode_state(self.x, self.ap, 0, self.step_ns, self._state_msg, self._clock_msg, self._scratch)
        self._measure()
        self._last_publish = time.monotonic()
        self._published = False

    def _initial_state(self) -> np.ndarray:
        """(y, ẏ, P1, P2, spool): the plant at rest (SPEC §4, with its own
        parameters), the spool centred."""
        return steps.plant_state(self.actuator.initial_state())

    def start(self) -> None:
        """Run an episode from the current state (lock-step: publishes it now;
        realtime: the executor's owner runs :meth:`run_realtime`); only when active."""
        if not self.active:
            self.get_logger().warning(f"~/start refused: the plant is {state_label(self)}, not active")
            return
        self.finished = False
        self.started_at = time.perf_counter()
        self._first_sample = self.sample
        if self.mode == "realtime":
            self.run_requested = True
        else:
            self.publish_state()

    def first_answer_timeout(self) -> float:
        """How long the first sample of a run waits [s]: ``startup_timeout`` while a
        matched controller has not answered yet, else ``command_timeout``."""
        return self.startup_timeout if self.connected() else self.timeout

    def connected(self) -> bool:
        """Both directions of the loop have matched a peer (a controller is listening and talking)."""
        return bool(self.state_pub.get_subscription_count() and self._command_sub.get_publisher_count())

    def _measure(self) -> None:
        """With measured states: the true state just encoded moves to ``true_state``,
        the sensors' readings of it (seeded noise of this sample) take its place."""
        if self.measured:
            self._true_msg[:] = self._state_msg
            steps.encode_measured(self.x, self.ap, self.sample, self.step_ns, self.sp, self.seed,
                                  self._state_msg, self._clock_msg, self._scratch)

    def publish_state(self) -> None:
        """Write: the state of the current sample (with measured states, then the
        true state), then its clock (the state first: it is what the controller
        waits on; the clock's publish no longer delays it)."""
        try:
            self._publish_state(bytes(self._state_msg))
            if self.measured:
                self._publish_true(bytes(self._true_msg))
            self._publish_clock(bytes(self._clock_msg))
        except _rclpy.RCLError as exc:           # DDS refused the write (a reader gone, a full history)
            self.publish_failures += 1            # the sample goes unanswered: a miss, not a crash
            self.get_logger().warning(f"sample {self.sample} not published ({str(exc).split(',')[0]}); "
                                      f"{self.publish_failures} so far", throttle_duration_sec=5.0)
        self._last_publish = time.monotonic()
        self._published = True

    def step(self, u: float, answered: bool = True) -> bool:
        """Update: advance one sample with valve command u [m] (``answered``: the
        controller's answer to it, not a held or fail-safe value); False when the
        episode ends (the diverged state is then published, for the record)."""
        if self.log is not None:
            self.log.append((self.sample, *map(float, self.x[:4]), u))
        k = self.sample % ANSWERS_KEPT
        self._answered_at[k], self._answers[k] = (self.sample, u) if answered else (-1, 0.0)
        self.sample += 1
        bad = steps.plant_sample(self.x, u, self.ap, self.step_s, self.y_limit, self.sample, self.step_ns,
                                 self._state_msg, self._clock_msg, self._scratch)
        self._measure()
        if self.samples and self.sample >= self.samples:
            self._finish()
            return False
        if bad:
            self.get_logger().error(f"diverged at sample {self.sample}: y = {self.x[0]:.4g} m")
            self.publish_state()
            self.diverged = True
            self._finish()
            return False
        return True

    def _finish(self) -> None:
        self.finished = True
        self.run_seconds = time.perf_counter() - self.started_at

    def _on_command(self, data: bytes) -> None:
        """Read: keep the latest command; in lock-step, the awaited one advances the plant."""
        if not self.active:
            return
        i, u = steps.command_of(data, self.step_ns, self._scratch)
        if i < 0:
            i, u = self._decode_other_layout(data, i)
            if i < 0:
                return
        k = i % ANSWERS_KEPT
        if (i == self.command_sample and u != self.command_u) or (
                i < self.sample and self._answered_at[k] == i and self._answers[k] != u):
            self._conflict(f"two different commands for sample {i}")
        if i >= self.command_sample:
            self.command_sample, self.command_u = i, u
        if self.mode == "realtime" or self.finished or not self._published or i != self.sample:
            return                                   # stale or early: not the sample we wait on
        if self._in_outage:
            self.commands_back()
        if self.step(u):
            self.publish_state()

    def _decode_other_layout(self, data: bytes, status: int) -> tuple[int, float]:
        """A command the fast decoder refused: a JointState of another layout
        (a frame_id, velocities, more joints) is read by name; anything else is
        counted and ignored."""
        if status != NOT_FINITE:
            try:
                from rclpy.serialization import deserialize_message
                msg = deserialize_message(data, JointState)
                u = float(msg.position[list(msg.name).index(COMMAND_NAMES[0])])
                ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                if ns >= 0 and ns % self.step_ns == 0:              # on the sample grid, as the fast path asks
                    if math.isfinite(u):
                        return ns // self.step_ns, u
                    status = NOT_FINITE
            except Exception:                        # noqa: BLE001 - any undecodable bytes
                pass
        self.malformed_commands += 1
        what = "a non-finite value" if status == NOT_FINITE else "not a valve JointState on the sample grid"
        self.get_logger().warning(f"refused a command ({what}); {self.malformed_commands} so far",
                                  throttle_duration_sec=5.0)
        return -1, 0.0

    def _conflict(self, what: str) -> None:
        """Another controller answers on our command topic: the run's numbers are no
        longer this loop's. Counted (``conflicts``) and logged; ``stack`` fails on it."""
        self.conflicts += 1
        if self.stop_on_conflict:
            self.finished = True
        self.get_logger().error(
            f"{what}: {self.count_publishers(self._command_topic)} publishers on {self._command_topic}; "
            f"{self.conflicts} conflicting commands so far", throttle_duration_sec=5.0)

    def failsafe(self, missing: int) -> None:
        """The valve is centred for this sample (``missing`` commands in a row)."""
        self.failsafe_events += 1
        if not self._in_outage:
            self.get_logger().warning(f"no command for {missing} samples at sample {self.sample}: "
                                      "valve centred (u = 0) until commands return")
            self._in_outage = True

    def commands_back(self) -> None:
        self.get_logger().info(f"commands are back at sample {self.sample}")
        self._in_outage = False

    # --- lock-step timing ------------------------------------------------------
    def _check_deadline(self) -> None:
        if self.finished or not self._published:
            return
        waited = time.monotonic() - self._last_publish
        limit = self.first_answer_timeout() if self.sample == self._first_sample else self.timeout
        if waited > limit:
            self.failsafe(1)
            if self.step(0.0, answered=False):
                self.publish_state()
        elif waited > self.timeout / 4:
            # A controller that has just matched may not have had the state (or we
            # its answer): send it again (not to observers); a repeat gets the same command.
            self.state_pub.publish(bytes(self._state_msg))

    def _report_lockstep(self) -> None:
        now, done = time.monotonic(), self.sample
        then, before = self._last_report
        self._last_report = (now, done)
        self._diagnose({"rate_hz": (done - before) / (now - then), "samples": float(done),
                        "failsafe_samples": float(self.failsafe_events),
                        "malformed_commands": float(self.malformed_commands),
                        "conflicts": float(self.conflicts)}, "lock-step loop")

    # --- realtime ------------------------------------------------------------
    def run_realtime(self, executor, on_second=None) -> LoopStats:
        """Run the requested episode paced to wall time on this thread, which
        must own ``executor`` (see :mod:`has_control.nodes.pacing`)."""
        self.run_requested = False
        if not self._published:
            self.started_at = time.perf_counter()

        def each_second(stats: LoopStats) -> None:
            self._report_realtime(stats)
            if on_second is not None:
                on_second(stats)
        stats = run_paced(executor, self, priority=self.priority, on_second=each_second)
        self._report_realtime(stats)
        st = self.realtime_stats
        self.get_logger().info(
            f"realtime: {st['rate_hz']:.0f} samples/s, real-time factor {st['realtime_factor']:.4f}, "
            f"{st['missed_samples']:.0f} missed, {st['failsafe_samples']:.0f} fail-safe, lateness p50 "
            f"{st['late_p50_us']:.0f} us, p99 {st['late_p99_us']:.0f} us, max {st['late_max_us']:.0f} us, "
            f"{st['overruns']:.0f} overruns")
        return stats

    def _report_realtime(self, stats: LoopStats) -> None:
        st = stats.as_dict()
        st["failsafe_events"] = float(self.failsafe_events)
        st["malformed_commands"] = float(self.malformed_commands)
        st["conflicts"] = float(self.conflicts)
        self.realtime_stats = st
        self._diagnose(st, "realtime loop", ok=st["realtime_factor"] >= 0.99 and not stats.failsafe)

    def _diagnose(self, values: dict[str, float], what: str, ok: bool | None = None) -> None:
        if ok is None:
            ok = not self._in_outage
        message = ", ".join(f"{k} {v:.6g}" for k, v in values.items() if k in
                            ("rate_hz", "realtime_factor", "missed_samples", "failsafe_samples", "late_p99_us"))
        status = DiagnosticStatus(
            level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
            name=f"{self.get_fully_qualified_name()}: {what}", message=message,
            hardware_id="has_control plant",
            values=[KeyValue(key=k, value=f"{v:.6g}") for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(msg)


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
            node.run_realtime(executor)
        else:
            executor.spin_once(timeout_sec=0.05)
        if node.finished and node.run_seconds:
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
