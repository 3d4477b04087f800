"""Plant and controller composed in one process on the EventsExecutor.

rclpy has no component container; this is the composition. Used by
``has-control stack`` and by the tests that prove a graph run equals the
in-process trace.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rclpy
from rclpy.experimental import EventsExecutor
from rclpy.parameter import Parameter

from ..cost import Score, score_arrays
from ..params import Config
from .controller_node import ControllerNode
from .plant_node import PlantNode


@dataclass
class StackRun:
    trace: np.ndarray          # rows (t, x1d, y, ẏ, P1, P2, u, e1, e2, e3, â1, â2)
    score: Score
    seconds: float
    failsafe_events: int
    bag: Path | None = None


def _overrides(cfg: Config) -> list[Parameter]:
    from ..config import config_parameters
    return [Parameter(k, value=v) for k, v in config_parameters(cfg).items()]


def _plant_parameters(params: list[Parameter]) -> list[Parameter]:
    """The plant's share of a Config's parameters (actuator.*, simulation.*)."""
    from .plant_node import PREFIXES
    return [p for p in params if p.name.startswith(PREFIXES)]


def run_stack(cfg: Config | None = None, gains=None, namespace: str = "",
              publish_internals: bool = False, args: list[str] | None = None,
              context: rclpy.Context | None = None, timeout: float = 600.0,
              domain_id: int | None = None, record: str | Path | None = None) -> StackRun:
    """Run one lock-step episode through plant and controller nodes in this process.

    ``record``: also record the run to a rosbag2 MCAP bag at this path (a
    recorder node in the same executor; the controller then publishes its
    internals, which the bag needs for scoring).
    """
    from ..config import build_config
    cfg = cfg or Config()
    if gains is not None:
        cfg = build_config({"gains.k1": float(gains[0]), "gains.k2": float(gains[1]),
                            "gains.k3": float(gains[2])}, source="--gains", base=cfg)
    own = context is None
    if own:
        context = rclpy.Context()
        rclpy.init(args=args, context=context, domain_id=domain_id)
    try:
        params = _overrides(cfg)
        n = cfg.episode.samples
        plant = PlantNode(namespace=namespace, context=context,
                          parameter_overrides=_plant_parameters(params) + [Parameter("samples", value=n)])
        internals = publish_internals or record is not None
        controller = ControllerNode(namespace=namespace, context=context,
                                    parameter_overrides=params + [Parameter("publish_internals", value=internals)])
        controller.log = []
        executor = EventsExecutor(context=context)
        nodes = [plant, controller]
        recorder = None
        if record is not None:
            from .recorder import Recorder
            rec_node = rclpy.create_node("recorder", namespace=namespace, context=context)
            recorder = Recorder(rec_node, namespace)
            recorder.open(record, cfg)
            nodes.append(rec_node)
        for node in nodes:
            executor.add_node(node)
        t0 = time.perf_counter()
        _wait_for_match(executor, plant, controller, recorder)
        plant.start()
        deadline = time.monotonic() + timeout
        while not plant.finished and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        seconds = time.perf_counter() - t0
        trace = np.array(controller.log).reshape(-1, 12)
        bag = None
        if recorder is not None:
            _drain(executor, recorder, len(trace))
            bag = recorder.close()
        diverged = plant.diverged or len(trace) < n
        trace = trace[:n]
        score = score_arrays(trace[:, 7], trace[:, 6], cfg.episode.as_array(), diverged=diverged)
        run = StackRun(trace, score, seconds, plant.failsafe_events, bag)
        executor.shutdown()
        for node in nodes:
            node.destroy_node()
        return run
    finally:
        if own:
            rclpy.try_shutdown(context=context)


def _wait_for_match(executor, plant, controller, recorder=None, timeout: float = 10.0) -> None:
    """Spin until both directions of the loop (and the recorder) have discovered each other."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if (plant.state_pub.get_subscription_count() and controller.command_pub.get_subscription_count()
                and (recorder is None or recorder.connected())):
            return
        executor.spin_once(timeout_sec=0.01)
    raise RuntimeError("plant and controller did not discover each other within "
                       f"{timeout:g} s (ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})")


def _drain(executor, recorder, commands: int, timeout: float = 10.0) -> None:
    """Spin until the recorder holds every message the run published."""
    from ..bag import COMMAND, CONTROLLER_STATE, REFERENCE, STATE
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if all(recorder.count(t) >= commands for t in (STATE, COMMAND, REFERENCE, CONTROLLER_STATE)):
            return
        executor.spin_once(timeout_sec=0.01)
    counts = {t: recorder.count(t) for t in (STATE, COMMAND, REFERENCE, CONTROLLER_STATE)}
    raise RuntimeError(f"recorder missed messages: {counts}, expected {commands} each")


def run_tuning_stack(cfg: Config, changes: dict, config_files=(), evaluator: str = "batch",
                     namespaces: list[str] | None = None, record: str | None = None,
                     validate_best: bool = True, context: rclpy.Context | None = None,
                     domain_id: int | None = None, timeout: float = 3600.0, log_every: int = 1) -> dict:
    """Plant and controller (one pair per namespace) and the tuner node in one
    process on the EventsExecutor; returns the tuner's result dict.

    ``changes``: swarm settings (seed, particles, iterations, variant) over
    config/tuner.yaml and ``config_files``.
    """
    from ..tuning import load_tuning
    from .tuner_node import TunerNode, tuning_parameters
    tuning = load_tuning(config_files).replace(**changes)
    namespaces = namespaces or [""]
    own = context is None
    if own:
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=domain_id)
    try:
        model = _overrides(cfg)
        nodes = []
        for ns in namespaces:
            nodes.append(PlantNode(namespace=ns, context=context, parameter_overrides=_plant_parameters(model)))
            nodes.append(ControllerNode(namespace=ns, context=context, parameter_overrides=model))
        tuner = TunerNode(context=context, parameter_overrides=model + [
            Parameter(k, value=v) for k, v in tuning_parameters(tuning).items()] + [
            Parameter("evaluator", value=evaluator), Parameter("lanes", value=list(namespaces)),
            Parameter("validate_best", value=validate_best), Parameter("record", value=record or ""),
            Parameter("log_every", value=log_every)])
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
            from ..errors import HasControlError
            raise HasControlError(tuner.error)
        if tuner.result is None:
            raise RuntimeError(f"the tuner did not finish within {timeout:g} s")
        return tuner.result
    finally:
        if own:
            rclpy.try_shutdown(context=context)
