"""Plant and controller composed in one process on the EventsExecutor.

rclpy has no component container; this is the composition. Used by
``has-control stack`` and by the tests that prove a graph run equals the
in-process trace.
"""
from __future__ import annotations

import gc
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import rclpy
from rclpy.logging import LoggingSeverity
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter

from has_control.core.cost import Score, score_arrays
from has_control.core.params import Config
from has_control.nodes.controller_node import ControllerNode
from has_control.nodes.managed import bring_up
from has_control.nodes.runtime import borrowed_context, normalise_namespace, tap_diagnostics, tee
from has_control.wire.run_messages import run_of_messages
from has_control.wire.topics import (COMMAND, CONTROLLER_STATE, FLOAT64_ARRAY, JOINT_STATE, MEASURED_RUN_TOPICS,
                                     MISSED, RUN_TOPICS, STATE, TRUE_STATE)
from has_control.common.errors import HasControlError
from has_control.config import build_config, config_parameters
from has_control.core.episode import Col, EpisodeArrays
from has_control.core.run import Run
from has_control.nodes.plant_node import PREFIXES, PlantNode
from has_control.nodes.recorder import Recorder, topic_name
from has_control.nodes.tuner_node import TunerNode
from has_control.tuning.tuner import load_tuning, tuning_parameters


@dataclass
class StackRun:
    run: Run                   # what the loop ran: states, commands, reference, the controller's internals
    score: Score
    seconds: float             # wall time, set-up included
    failsafe_events: int
    bag: Path | None = None
    loop: dict = field(default_factory=dict)   # the loop's figures (see :func:`loop_figures`)
    missed_at: list[int] = field(default_factory=list)   # realtime: samples that ran on a held command
    close_seconds: float = 0.0                 # closing the bag after the loop (what is left to write)

    @property
    def trace(self) -> np.ndarray:
        """The run's (samples, 12) array (:attr:`Run.data`), as the tests and ``scripts/bench`` read it."""
        return self.run.data


def _overrides(cfg: Config) -> list[Parameter]:
    return [Parameter(k, value=v) for k, v in config_parameters(cfg).items()]


def _plant_parameters(params: list[Parameter]) -> list[Parameter]:
    """The plant's share of a Config's parameters (actuator.*, simulation.*)."""
    return [p for p in params if p.name.startswith(PREFIXES)]


def loop_figures(samples: int, seconds: float, step: float, failsafe: int, paced: dict | None = None) -> dict:
    """``samples_per_second`` (the loop's rate after start-up), ``realtime_factor``
    (simulation time / wall time), ``missed_samples``, ``failsafe_samples`` and
    ``late_p99_us`` (paced runs only; None in lock-step)."""
    if paced:
        return {"samples_per_second": paced["rate_hz"], "realtime_factor": paced["realtime_factor"],
                "missed_samples": int(paced["missed_samples"]), "failsafe_samples": int(paced["failsafe_samples"]),
                "late_p99_us": paced["late_p99_us"]}
    return {"samples_per_second": samples / seconds if seconds else None,
            "realtime_factor": samples * step / seconds if seconds else None,
            "missed_samples": 0, "failsafe_samples": failsafe, "late_p99_us": None}


def run_stack(cfg: Config | None = None, gains=None, namespace: str = "",
              publish_internals: bool = False, args: list[str] | None = None,
              context: rclpy.Context | None = None, timeout: float = 600.0,
              domain_id: int | None = None, record: str | Path | None = None,
              realtime: bool = False, priority: int = 50,
              progress: Callable[[int, int, float], None] | None = None,
              foxglove: int | None = None, foxglove_wait: float = 0.0,
              announce: Callable[[str], None] | None = None) -> StackRun:
    """Run one episode through plant and controller nodes composed in this
    process (the ros2_control layout), lock-step or, with ``realtime``, paced
    to wall time (SCHED_FIFO at ``priority`` where permitted).

    The run and its score are what the recorder took from the bytes the nodes
    publish (:func:`~has_control.wire.run_messages.run_of_messages`; the
    controller hands it its internals, published on ``~/controller_state`` and
    ``~/reference`` with ``publish_internals`` or ``record``). ``record``: also
    write them to a rosbag2 MCAP bag at this path. ``progress(samples done, samples,
    samples/s)`` is called about once a second. ``foxglove``: also serve the
    run's topics live on a Foxglove WebSocket at this port of 127.0.0.1 for the
    run, from a viewer process (:class:`~has_control.nodes.live_process.LiveViewProcess`:
    the loop only copies each message into a ring); ``announce(line)`` hears its
    URL before the run starts, and the run waits up to ``foxglove_wait`` seconds
    for a client to subscribe.
    """
    cfg = cfg or Config()
    namespace = normalise_namespace(namespace)
    if gains is not None:
        cfg = build_config({"gains.k1": float(gains[0]), "gains.k2": float(gains[1]),
                            "gains.k3": float(gains[2])}, source="--gains", base=cfg)
    with borrowed_context(context, args=args, domain_id=domain_id) as context, _live_view(foxglove) as live:
        t0 = time.perf_counter()
        if live is not None and announce is not None:
            announce(f"serving live on ws://127.0.0.1:{live.port} (Foxglove: open a WebSocket connection; "
                     "layout config/foxglove/has_control.json)")
        stack = _Composed(namespace=namespace)
        interrupted: list = []
        try:
            stack.compose(cfg, context, record, live, realtime, priority, publish_internals)
            if live is not None and foxglove_wait > 0:
                if announce is not None:
                    announce(f"waiting up to {foxglove_wait:g} s for a Foxglove client")
                live.wait_for_client(foxglove_wait)
            loop = stack.run(cfg, realtime, timeout, progress, interrupted)
        finally:                                 # a clean bag and no nodes left, whatever happened
            bag, close_seconds = stack.close()
        if interrupted:
            raise KeyboardInterrupt              # after the bag is closed: the caller says "interrupted"
        return stack.result(cfg, loop, bag, close_seconds, time.perf_counter() - t0)


@dataclass
class _Loop:
    """What one run of the loop measured: the pacing figures (None in lock-step),
    the samples missed, and the loop's wall time [s]."""

    paced: dict | None
    missed_at: list
    seconds: float


@dataclass
class _Composed:
    """Plant and controller composed in this process around one executor, with
    the recorder: built by :meth:`compose`, run by :meth:`run`, closed by
    :meth:`close` whatever happened, read by :meth:`result`."""

    namespace: str
    plant: PlantNode | None = None
    controller: ControllerNode | None = None
    executor: EventsExecutor | None = None
    recorder: Recorder | None = None
    nodes: list = field(default_factory=list)
    measured: bool = False

    def compose(self, cfg: Config, context, record, live, realtime: bool, priority: int,
                publish_internals: bool) -> None:
        """The recorder, both nodes (brought up: unconfigured -> inactive -> active)
        and the executor, matched to each other."""
        params, n = _overrides(cfg), cfg.episode.samples
        self.measured = cfg.noise.added_by == "plant"   # the controller reads readings: the truth is the plant's
        run = _run_topics(self.measured, realtime)
        if record is not None:
            topics = {**(MEASURED_RUN_TOPICS if self.measured else RUN_TOPICS), **run}
            self.recorder = Recorder(namespace=self.namespace, subscribe=False, process=True, topics=topics,
                                     keep=run)
            self.recorder.open(record, cfg)
        else:                                    # no bag: what the run needs, kept in memory
            self.recorder = Recorder(namespace=self.namespace, subscribe=False, topics=run, keep=run)
        tap = tee(self.recorder.sink, live and live.sink)
        managed = Parameter("autostart", value=False)           # the transitions are driven here
        self.plant = PlantNode(namespace=self.namespace, context=context, tap=tap, parameter_overrides=(
            _plant_parameters(params) + [Parameter("samples", value=n), Parameter("realtime_priority", value=priority),
                                         Parameter("mode", value="realtime" if realtime else "lockstep"), managed]))
        self.nodes.append(self.plant)
        self.controller = ControllerNode(namespace=self.namespace, context=context, tap=tap, parameter_overrides=(
            params + [Parameter("publish_internals", value=publish_internals or record is not None), managed]))
        self.nodes.append(self.controller)
        for node in (self.plant, self.controller):
            tap_diagnostics(node, live and live.sink)   # the live view serves /diagnostics too
            _bring_up(node)
        if realtime:                             # what the plant ran without its answer, to the recorder
            self.plant.process.on_unanswered = self.recorder.sink(topic_name(self.namespace, MISSED))
        self.executor = EventsExecutor(context=context)
        for node in self.nodes:
            self.executor.add_node(node)
        _wait_for_match(self.executor, self.plant, self.controller)

    def run(self, cfg: Config, realtime: bool, timeout: float, progress, interrupted: list) -> _Loop:
        """One episode, lock-step or paced, with the collector off and SIGINT/SIGTERM
        ending it at the next sample; a conflict (a stranger on the topics) ends it too."""
        plant, controller, n = self.plant, self.controller, cfg.episode.samples
        plant.stop_on_conflict = True        # a run with a stranger in it is over: fail it now

        def stop_if_conflicts() -> None:
            if controller.conflicts:
                plant.finished = True
        gc.collect()
        gc.disable()
        try:
            _stop_on_signals(plant, interrupted)
            started = time.perf_counter()
            plant.start()
            if realtime:
                def each_second(st) -> None:
                    stop_if_conflicts()
                    if progress is not None:
                        progress(st.samples, n, st.samples / max(st.wall_ns / 1e9, 1e-9))
                stats = plant.run(self.executor, on_second=each_second)
                return _Loop(stats.as_dict(), stats.missed_at, time.perf_counter() - started)
            plant.run(self.executor, on_second=_lockstep_progress(progress, n),
                      check=_lockstep_check(plant, timeout, stop_if_conflicts))
            return _Loop(None, [], time.perf_counter() - started)
        finally:
            gc.enable()
            _stop_on_signals(None, None)

    def close(self) -> tuple[Path | None, float]:
        """Close the bag (its time [s] measured) and destroy the nodes."""
        closing = time.perf_counter()
        bag = self.recorder.close() if self.recorder is not None else None     # None: no bag
        close_seconds = time.perf_counter() - closing
        if self.executor is not None:
            self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        return bag, close_seconds

    def result(self, cfg: Config, loop: _Loop, bag, close_seconds: float, seconds: float) -> StackRun:
        """The run the recorder took (:func:`run_of`) and its score; a run with a stranger in it is refused."""
        plant, controller, n = self.plant, self.controller, cfg.episode.samples
        run = run_of(self.recorder, cfg, self.measured)
        bad = ~np.isfinite(run.data[:, Col.y:Col.P2 + 1]).all(axis=1) | (np.abs(run.y) > cfg.episode.y_limit)
        diverged = len(run) < n or bool(bad.any()) or not np.all(np.isfinite(run.u))
        score = score_arrays(run.e1, run.u, cfg.episode.as_array(), diverged=diverged)
        conflicts = (plant.conflicts, controller.conflicts)
        if any(conflicts):
            raise HasControlError(
                f"namespace '{self.namespace or '/'}': another node publishes on this loop's topics "
                f"({conflicts[0]} samples answered twice, {conflicts[1]} states out of order); "
                "the numbers would not be this run's: use another --namespace or ROS_DOMAIN_ID")
        figures = loop_figures(plant.sample, loop.seconds, cfg.episode.step, plant.failsafe_events, loop.paced)
        return StackRun(run, score, seconds, plant.failsafe_events, bag, figures, loop.missed_at, close_seconds)


def _run_topics(measured: bool, realtime: bool) -> dict[str, str]:
    """The topics a stack's run is made of (:func:`run_of`): the plant's true
    states, the commands, the controller's internals, and in a paced run the
    samples the plant ran without their command."""
    return {TRUE_STATE if measured else STATE: JOINT_STATE, COMMAND: JOINT_STATE, CONTROLLER_STATE: FLOAT64_ARRAY,
            **({MISSED: FLOAT64_ARRAY} if realtime else {})}


def run_of(recorder: Recorder, cfg: Config, measured: bool) -> Run:
    """The run ``recorder`` took (:func:`~has_control.wire.run_messages.run_of_messages`)."""
    ep = cfg.episode
    return run_of_messages(recorder.taken(TRUE_STATE if measured else STATE), recorder.taken(COMMAND),
                           recorder.taken(CONTROLLER_STATE), recorder.taken(MISSED), ep.step, ep.step_ns,
                           EpisodeArrays.from_config(cfg).reference)


def _bring_up(node) -> None:
    """Configure and activate ``node``; a refusal is one line naming it."""
    node.quiet = True                            # the stack's own lines say what runs
    try:
        bring_up(node)
    except ValueError as exc:
        raise HasControlError(f"{node.get_fully_qualified_name()}: {exc}") from None


def _live_view(port: int | None):
    """The Foxglove live view on ``port`` (None: none). Opened before the bag, so
    a port in use ends the run before a bag exists; closed with the run."""
    if port is None:
        from contextlib import nullcontext
        return nullcontext()
    # lazy: foxglove-sdk is an optional dependency (the "live" extra); only --foxglove needs it
    from has_control.nodes.live_process import LiveViewProcess
    return LiveViewProcess(port)


def _refuse_strangers(plant, controller) -> None:
    """Another publisher on the loop's state or command topic (a second
    controller, a second stack in this namespace) would mix its numbers into
    this run: refuse to start."""
    for node, topic in ((plant, controller._state_topic), (controller, plant._command_topic)):
        n = node.count_publishers(topic)
        if n > 1:
            raise HasControlError(f"{topic}: {n} publishers; another node publishes on this loop's topics, "
                                  "so the numbers would not be this run's: use another --namespace or ROS_DOMAIN_ID")


def _stop_on_signals(plant, interrupted: list | None) -> None:
    """While a run goes (``plant`` given): Ctrl-C and SIGTERM end the episode at
    the next sample instead of raising inside an rclpy callback; afterwards
    (``plant`` None) the previous handlers are back."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        return
    if plant is None:
        for sig, handler in _previous.items():
            signal.signal(sig, handler)
        _previous.clear()
        return

    def stop(signum, frame):
        interrupted.append(signum)
        plant.finished = True
        # the run's summary lines are for a finished run: an interrupted one ends in one line, "interrupted"
        plant.get_logger().set_level(LoggingSeverity.WARN)
    for sig in (signal.SIGINT, signal.SIGTERM):
        _previous[sig] = signal.signal(sig, stop)


_previous: dict = {}


def _lockstep_check(plant, timeout: float, check):
    """``check()`` after every burst of lock-step events; past ``timeout`` [s] the run is over."""
    deadline = time.monotonic() + timeout

    def each_burst() -> None:
        check()
        if time.monotonic() > deadline:
            plant.finished = True
    return each_burst


def _lockstep_progress(progress, samples: int):
    """``progress(done, samples, rate over the last second)`` once a second, or None."""
    if progress is None:
        return None
    last = [time.perf_counter(), 0]

    def each_second(stats) -> None:
        t, done = time.perf_counter(), stats.samples
        if done:
            progress(done, samples, (done - last[1]) / (t - last[0]))
        last[:] = [t, done]
    return each_second


def _wait_for_match(executor, plant, controller, timeout: float = 10.0) -> None:
    """Spin until both directions of the loop have discovered each other."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if plant.state_pub.get_subscription_count() and controller.command_pub.get_subscription_count():
            _refuse_strangers(plant, controller)
            return
        executor.spin_once(timeout_sec=0.01)
    raise RuntimeError("plant and controller did not discover each other within "
                       f"{timeout:g} s (ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})")


def run_tuning_stack(cfg: Config, changes: dict, config_files=(), evaluator: str = "batch",
                     namespaces: list[str] | None = None, record: str | None = None,
                     validate_best: bool = True, context: rclpy.Context | None = None,
                     domain_id: int | None = None, timeout: float = 3600.0, log_every: int = 1,
                     scenarios: str | None = None, aggregate: str = "mean", keep_episodes: bool = False) -> dict:
    """Plant and controller (one pair per namespace) and the tuner node in one
    process on the EventsExecutor; returns the tuner's result dict.

    ``changes``: swarm settings (seed, particles, iterations, variant) over
    config/tuner.yaml and ``config_files``. ``keep_episodes``: keep one bag per
    graph episode under ``record/episodes``. ``scenarios``: a scenario file
    (robust tuning, batch evaluator) scored by ``aggregate``.
    """
    tuning = load_tuning(config_files).replace(**changes)
    namespaces = [normalise_namespace(ns) for ns in namespaces or [""]]
    with borrowed_context(context, domain_id=domain_id) as context:
        model = _overrides(cfg)
        nodes = []
        for ns in namespaces:
            nodes.append(PlantNode(namespace=ns, context=context, parameter_overrides=_plant_parameters(model)))
            nodes.append(ControllerNode(namespace=ns, context=context, parameter_overrides=model))
        tuner = TunerNode(context=context, parameter_overrides=model + [
            Parameter(k, value=v) for k, v in tuning_parameters(tuning).items()] + [
            Parameter("evaluator", value=evaluator), Parameter("lanes", value=list(namespaces)),
            Parameter("validate_best", value=validate_best), Parameter("record", value=record or ""),
            Parameter("log_every", value=log_every), Parameter("scenarios", value=str(scenarios or "")),
            Parameter("aggregate", value=aggregate), Parameter("keep_episodes", value=keep_episodes)])
        nodes.append(tuner)
        executor = EventsExecutor(context=context)
        for node in nodes:
            executor.add_node(node)
        tuner.start()
        deadline = time.monotonic() + timeout
        while not tuner.done.is_set() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        if tuner.error:
            raise HasControlError(tuner.error)
        if tuner.result is None:
            raise RuntimeError(f"the tuner did not finish within {timeout:g} s")
        return tuner.result
