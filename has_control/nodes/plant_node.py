"""The plant node: simulates the actuator at one 0.3 ms step per sample.

Every step calls :func:`has_control.actuator.plant_step`, the one
implementation, so a run through the graph equals the in-process trace.

``mode: lockstep`` (default): publish state i, wait for command i, advance,
publish state i + 1. If no command arrives within ``command_timeout`` seconds
of wall time, the fail-safe applies u = 0 (valve centred) to that sample,
warns once per outage and counts the event; control resumes when commands
return. A diverged state (|y| > y_limit or not finite) is published and ends
the episode.

``mode: realtime``: a dedicated thread steps the plant against the wall clock
every ``simulation.step`` (a ROS timer cannot hold 0.3 ms in rclpy), holding
the latest command (zero-order hold). Without a command for
``failsafe_samples`` samples it centres the valve. Achieved rate, jitter
percentiles and overruns go to ``/diagnostics`` (diagnostic_msgs) once a
second and into :attr:`PlantNode.realtime_stats`.

Topics: ``state`` (sensor_msgs/JointState, out), ``command``
(sensor_msgs/JointState, in), ``clock`` (rosgraph_msgs/Clock, out; resolves to
``/clock`` in the root namespace, remap it there under a namespace).
Services (std_srvs/Trigger): ``~/reset`` back to the initial state at sample
0 and idle; ``~/start`` publish the current state and run an episode of
``samples`` samples (0: until stopped).
Parameters: ``actuator.*``, ``simulation.*``, ``mode``, ``samples``,
``command_timeout`` [s], ``failsafe_samples``, ``autostart`` (``main`` starts
the first episode when a controller connects), ``keep_alive`` (``main`` keeps
serving ``~/start`` after an episode instead of exiting).
"""
from __future__ import annotations

import threading
import time

import numpy as np
import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from ..actuator import plant_step
from .messages import CONTROL_QOS, sample_of, stamp, state_message, trigger_service
from .parameters import config_from_node, declare_config

PREFIXES = ("actuator.", "simulation.")
MODES = ("lockstep", "realtime")


class PlantNode(Node):
    def __init__(self, name: str = "plant", **kwargs):
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES)
        self.declare_parameter("mode", "lockstep")
        self.declare_parameter("command_timeout", 0.5)
        self.declare_parameter("failsafe_samples", 10)
        self.declare_parameter("samples", 0)        # 0: run until stopped
        self.declare_parameter("autostart", True)
        self.declare_parameter("keep_alive", False)
        cfg = config_from_node(self, PREFIXES)
        self.actuator = cfg.actuator
        self.ap = cfg.actuator.as_array()
        self.step = cfg.episode.step
        self.step_ns = int(round(self.step * 1e9))
        self.y_limit = cfg.episode.y_limit
        self.samples = int(self.get_parameter("samples").value)
        self.timeout = float(self.get_parameter("command_timeout").value)
        self.failsafe_samples = int(self.get_parameter("failsafe_samples").value)
        self.mode = self.get_parameter("mode").value
        if self.mode not in MODES:
            raise ValueError(f"parameter mode = {self.mode!r}: expected one of {', '.join(MODES)}")
        x0 = self.actuator.initial_state()
        plant_step(x0[0], x0[1], x0[2], x0[3], 0.0, self.ap, self.step)   # compile before joining the graph
        self.state_pub = self.create_publisher(JointState, "state", CONTROL_QOS)
        self.clock_pub = self.create_publisher(Clock, "clock", 10)
        sub = self.create_subscription(JointState, "command", self._on_command, CONTROL_QOS)
        self._command_topic = sub.topic_name
        trigger_service(self, "~/reset", self._reset_state, "plant at the initial state, sample 0, idle")
        trigger_service(self, "~/start", self.start, "episode started")
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.failsafe_events = 0
        self.started_at = self.run_seconds = 0.0
        self._in_outage = False
        self.finished = False
        self.diverged = False
        self.log: list[tuple[int, float, float, float, float, float]] | None = None
        self.realtime_stats: dict[str, float] = {}
        self._lock = threading.Lock()
        self._u_latest = 0.0
        self._u_sample = -1
        self._rt_thread: threading.Thread | None = None
        self._rt_stop = threading.Event()
        self._reset_state()
        if self.mode == "lockstep":
            self._watchdog = self.create_timer(max(self.timeout / 4, 0.01), self._check_deadline)
        else:
            from diagnostic_msgs.msg import DiagnosticArray
            self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)

    # --- parameters --------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        for p in params:
            if p.name == "samples" and (not isinstance(p.value, int) or p.value < 0):
                return SetParametersResult(successful=False, reason=f"samples = {p.value!r}: must be an integer >= 0")
            if p.name == "command_timeout" and not (isinstance(p.value, float) and p.value > 0):
                return SetParametersResult(successful=False,
                                           reason=f"command_timeout = {p.value!r}: must be a number > 0 [s]")
            if p.name.startswith(PREFIXES) or p.name == "mode":
                return SetParametersResult(successful=False,
                                           reason=f"{p.name}: read at start-up only; restart the plant to change it")
        for p in params:
            if p.name == "samples":
                self.samples = p.value
            elif p.name == "command_timeout":
                self.timeout = p.value
        return SetParametersResult(successful=True)

    # --- state -------------------------------------------------------------
    def _reset_state(self) -> None:
        """Back to the initial state at sample 0, idle until :meth:`start`."""
        self._rt_stop.set()
        if self._rt_thread is not None and self._rt_thread is not threading.current_thread():
            self._rt_thread.join()
        self._rt_thread = None
        self.x = self.actuator.initial_state()
        self.sample = 0
        self.finished = False
        self.diverged = False
        self._last_publish = time.monotonic()
        self._published = False

    def start(self) -> None:
        """Run an episode from the current state (publishes it first)."""
        self.finished = False
        self.started_at = time.perf_counter()
        if self.mode == "realtime":
            self._rt_stop.clear()
            self._rt_thread = threading.Thread(target=self._realtime_loop, name="plant-realtime", daemon=True)
            self._rt_thread.start()
        else:
            self._publish()

    def wait_realtime(self, timeout: float | None = None) -> None:
        """Block until the realtime loop has ended (its last diagnostics are out)."""
        if self._rt_thread is not None:
            self._rt_thread.join(timeout)

    def connected(self) -> bool:
        """Both directions of the loop have a peer (a controller is listening and talking)."""
        return bool(self.state_pub.get_subscription_count()
                    and self.count_publishers(self._command_topic))

    def _publish(self) -> None:
        self.clock_pub.publish(Clock(clock=stamp(self.sample, self.step_ns)))
        self.state_pub.publish(state_message(self.sample, self.step_ns, self.x, self.actuator))
        self._last_publish = time.monotonic()
        self._published = True

    def _step(self, u: float) -> bool:
        """Advance one sample with valve command u [m]; False when the episode ends."""
        if self.log is not None:
            self.log.append((self.sample, *map(float, self.x), u))
        y, v, p1, p2 = plant_step(self.x[0], self.x[1], self.x[2], self.x[3], u, self.ap, self.step)
        self.x = np.array([y, v, p1, p2])
        self.sample += 1
        if self.samples and self.sample >= self.samples:
            self.finished = True
            self.run_seconds = time.perf_counter() - self.started_at
            return False
        if not np.all(np.isfinite(self.x)) or abs(y) > self.y_limit:
            self.get_logger().error(f"diverged at sample {self.sample}: y = {y:.4g} m")
            self._publish()                        # the diverged state, for the record
            self.finished = self.diverged = True
            self.run_seconds = time.perf_counter() - self.started_at
            return False
        return True

    def _advance(self, u: float) -> None:
        if self._step(u):
            self._publish()

    # --- lock-step callbacks -------------------------------------------------
    def _on_command(self, msg: JointState) -> None:
        i = sample_of(msg.header.stamp, self.step_ns)
        if self.mode == "realtime":
            with self._lock:
                self._u_latest, self._u_sample = float(msg.position[0]), i
            return
        if self.finished or not self._published or i != self.sample:
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

    # --- realtime ------------------------------------------------------------
    def _realtime_loop(self) -> None:
        """Step every Δt of wall time: sleep until just before, then spin to the deadline."""
        dt = self.step
        period_ns = self.step_ns
        t0 = time.perf_counter_ns()
        lateness: list[float] = []
        overruns = 0
        report_every = max(1, int(round(1.0 / dt)))
        self._publish()
        while not self._rt_stop.is_set():
            due = t0 + (self.sample + 1) * period_ns
            now = time.perf_counter_ns()
            if due - now > 120_000:
                time.sleep((due - now - 80_000) / 1e9)
            while (now := time.perf_counter_ns()) < due:
                time.sleep(0)                          # spin, but let the executor thread run
            late = (now - due) / 1e3                   # [µs]
            lateness.append(late)
            if late > period_ns / 1e3:
                overruns += 1
            with self._lock:
                u, answered = self._u_latest, self._u_sample
            missing = self.sample - answered
            if missing > self.failsafe_samples:
                if not self._in_outage:
                    self.get_logger().warning(
                        f"no command for {missing} samples at sample {self.sample}: valve centred (u = 0)")
                    self._in_outage = True
                self.failsafe_events += 1
                u = 0.0
            elif self._in_outage:
                self.get_logger().info(f"commands are back at sample {self.sample}")
                self._in_outage = False
            if not self._step(u):
                break
            self._publish()
            if self.sample % report_every == 0:
                self._report(lateness, overruns, now - t0)
        self._report(lateness, overruns, time.perf_counter_ns() - t0)

    def _report(self, lateness: list[float], overruns: int, elapsed_ns: int) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        if not lateness:
            return
        lat = np.asarray(lateness)
        stats = {"rate_hz": self.sample / (elapsed_ns / 1e9), "target_hz": 1.0 / self.step,
                 "jitter_p50_us": float(np.percentile(lat, 50)),
                 "jitter_p99_us": float(np.percentile(lat, 99)),
                 "jitter_max_us": float(lat.max()), "overruns": float(overruns),
                 "samples": float(self.sample), "failsafe_events": float(self.failsafe_events)}
        self.realtime_stats = stats
        ok = stats["rate_hz"] >= 0.99 * stats["target_hz"]
        status = DiagnosticStatus(
            level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
            name=f"{self.get_fully_qualified_name()}: realtime loop",
            message=f"{stats['rate_hz']:.0f} of {stats['target_hz']:.0f} samples/s, "
                    f"p99 jitter {stats['jitter_p99_us']:.0f} us",
            hardware_id="has_control plant",
            values=[KeyValue(key=k, value=f"{v:.6g}") for k, v in stats.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(msg)


def main(args=None):
    rclpy.init(args=args)
    node = PlantNode()
    keep_alive = bool(node.get_parameter("keep_alive").value)
    try:
        if node.get_parameter("autostart").value:
            while rclpy.ok() and not node.connected():
                rclpy.spin_once(node, timeout_sec=0.05)
            node.get_logger().info("controller connected: starting the run")
            node.start()
        else:
            node.get_logger().info("waiting for ~/start")
        while rclpy.ok() and (keep_alive or not node.finished):
            rclpy.spin_once(node, timeout_sec=0.1)
            if node.finished and node.run_seconds and keep_alive:
                _log_finished(node)
                node.run_seconds = 0.0
        if node.finished and not keep_alive:
            node.wait_realtime(5.0)
            _log_finished(node)
    except KeyboardInterrupt:
        pass
    finally:
        node._rt_stop.set()
        node.destroy_node()
        rclpy.try_shutdown()


def _log_finished(node: PlantNode) -> None:
    rate = node.sample / node.run_seconds if node.run_seconds else float("nan")
    node.get_logger().info(
        f"finished {node.sample} samples at t = {node.sample * node.step:.4f} s: "
        f"y = {node.x[0]:.9e} m, fail-safe events = {node.failsafe_events}, {rate:.0f} samples/s"
        + (" (diverged)" if node.diverged else ""))
    st = node.realtime_stats
    if st:
        node.get_logger().info(
            f"realtime: {st['rate_hz']:.0f} samples/s, jitter p50 {st['jitter_p50_us']:.1f} us, "
            f"p99 {st['jitter_p99_us']:.1f} us, max {st['jitter_max_us']:.1f} us, {st['overruns']:.0f} overruns")
