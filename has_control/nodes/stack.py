"""Plant and controller composed in one process on the EventsExecutor.

rclpy has no component container; this is the composition. Used by
``has-control stack`` and by the tests that prove a graph run equals the
in-process trace.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

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


def _overrides(cfg: Config) -> list[Parameter]:
    from ..config import config_parameters
    return [Parameter(k, value=v) for k, v in config_parameters(cfg).items()]


def run_stack(cfg: Config | None = None, gains=None, namespace: str = "",
              publish_internals: bool = False, args: list[str] | None = None,
              context: rclpy.Context | None = None, timeout: float = 600.0,
              domain_id: int | None = None) -> StackRun:
    """Run one lock-step episode through plant and controller nodes in this process."""
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
                          parameter_overrides=[p for p in params if p.name.startswith(("actuator.", "simulation."))]
                          + [Parameter("samples", value=n)])
        controller = ControllerNode(namespace=namespace, context=context,
                                    parameter_overrides=params + [Parameter("publish_internals", value=publish_internals)])
        controller.log = []
        executor = EventsExecutor(context=context)
        executor.add_node(plant)
        executor.add_node(controller)
        t0 = time.perf_counter()
        _wait_for_match(executor, plant, controller)
        plant.start()
        deadline = time.monotonic() + timeout
        while not plant.finished and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        seconds = time.perf_counter() - t0
        trace = np.array(controller.log).reshape(-1, 12)
        diverged = len(trace) < n
        score = score_arrays(trace[:, 7], trace[:, 6], cfg.episode.as_array(), diverged=diverged)
        run = StackRun(trace, score, seconds, plant.failsafe_events)
        executor.shutdown()
        plant.destroy_node()
        controller.destroy_node()
        return run
    finally:
        if own:
            rclpy.try_shutdown(context=context)


def _wait_for_match(executor, plant, controller, timeout: float = 10.0) -> None:
    """Spin until both directions of the loop have discovered each other."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if plant.state_pub.get_subscription_count() and controller.command_pub.get_subscription_count():
            return
        executor.spin_once(timeout_sec=0.01)
    raise RuntimeError("plant and controller did not discover each other within "
                       f"{timeout:g} s (ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})")
