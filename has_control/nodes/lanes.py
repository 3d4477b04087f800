"""The tuner's lanes: one plant/controller pair each, driven through services.

A :class:`Lane` is one plant/controller pair in a namespace, driven through
its services: set the gains, reset both, start the plant, record the episode
to a bag and score it from the bag. The lanes become a batch evaluator in
:class:`has_control.tuning.graph_evaluator.GraphEvaluator` (ROS-free), which the
tuner node hands to the session as ``batch``.
"""
from __future__ import annotations

import time
from pathlib import Path

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from std_srvs.srv import Trigger

from has_control.bag import BagError, score_bag
from has_control.common.errors import HasControlError
from has_control.tuning.graph_evaluator import UNSCORED
from has_control.nodes.recorder import Recorder
from has_control.nodes.runtime import normalise_namespace


def _wait(future, timeout: float, what: str):
    end = time.monotonic() + timeout
    while not future.done():
        if time.monotonic() > end:
            raise HasControlError(f"{what}: no answer within {timeout:g} s")
        time.sleep(0.0005)
    return future.result()


class Lane:
    """One plant/controller pair in ``namespace``, driven through services."""

    def __init__(self, node, namespace: str, controller: str, plant: str, y_limit: float):
        ns = normalise_namespace(namespace)        # sim0 is /sim0, as ROS resolves it
        self.namespace = ns or "/"
        self.controller_name, self.plant_name = f"{ns}/{controller}", f"{ns}/{plant}"
        self.controller_params = AsyncParameterClient(node, self.controller_name)
        self.plant_params = AsyncParameterClient(node, self.plant_name)
        self.controller_reset = node.create_client(Trigger, f"{self.controller_name}/reset")
        self.plant_reset = node.create_client(Trigger, f"{self.plant_name}/reset")
        self.plant_start = node.create_client(Trigger, f"{self.plant_name}/start")
        self.recorder = Recorder(node, ns, y_limit=y_limit)
        self.logger = node.get_logger()
        self.lifecycle = {name: (node.create_client(GetState, f"{name}/get_state"),
                                 node.create_client(ChangeState, f"{name}/change_state"))
                          for name in (self.plant_name, self.controller_name)}
        self.up: set[str] = set()
        self.samples = None                        # the plant's episode length, once set

    def bring_up(self) -> None:
        """Configure and activate the lane's managed nodes that are not active yet
        (a plant or controller started with ``autostart: false``)."""
        for name, (get, change) in self.lifecycle.items():
            if name in self.up or not get.service_is_ready():
                continue
            label = _wait(get.call_async(GetState.Request()), 10.0, get.srv_name).current_state.label
            for before, transition in (("unconfigured", Transition.TRANSITION_CONFIGURE),
                                       ("inactive", Transition.TRANSITION_ACTIVATE)):
                if label == before:
                    request = ChangeState.Request()
                    request.transition.id = transition
                    if not _wait(change.call_async(request), 60.0, change.srv_name).success:
                        raise HasControlError(f"{name}: refused the transition from {before} (see its log)")
                    self.logger.info(f"{name}: {before} -> {'inactive' if before == 'unconfigured' else 'active'}")
                    label = "inactive" if before == "unconfigured" else "active"
            if label == "active":
                self.up.add(name)

    def ready(self) -> bool:
        return (self.controller_params.services_are_ready() and self.plant_params.services_are_ready()
                and all(c.service_is_ready() for c in (self.controller_reset, self.plant_reset, self.plant_start))
                and self.recorder.connected())

    def _trigger(self, client, timeout: float = 10.0) -> None:
        res = _wait(client.call_async(Trigger.Request()), timeout, client.srv_name)
        if not res.success:
            raise HasControlError(f"{client.srv_name}: {res.message}")

    def set_parameters(self, client: AsyncParameterClient, params: list[Parameter], where: str) -> str | None:
        """None when accepted, else the reason."""
        res = _wait(client.set_parameters_atomically(params), 10.0, f"{where}/set_parameters_atomically")
        r = res.result
        return None if r.successful else (r.reason or "rejected")

    def set_gains(self, gains) -> str | None:
        return self.set_parameters(self.controller_params,
                                   [Parameter(f"gains.k{i + 1}", value=float(g)) for i, g in enumerate(gains)],
                                   self.controller_name)

    def gains(self) -> list[float]:
        res = _wait(self.controller_params.get_parameters(["gains.k1", "gains.k2", "gains.k3"]), 10.0,
                    f"{self.controller_name}/get_parameters")
        return [v.double_value for v in res.values]

    def parameters(self) -> dict[str, dict]:
        """The controller's and the plant's parameters as they are now, read back
        through their parameter services: {"controller": {name: value}, "plant": {...}}."""
        out = {}
        for role, client, name in (("controller", self.controller_params, self.controller_name),
                                   ("plant", self.plant_params, self.plant_name)):
            names = list(_wait(client.list_parameters(), 10.0, f"{name}/list_parameters").result.names)
            values = _wait(client.get_parameters(names), 10.0, f"{name}/get_parameters").values
            out[role] = {n: _python(v) for n, v in sorted(zip(names, values))}
        return out

    def prepare(self, cfg) -> None:
        """The plant runs episodes of ``cfg``'s length (set once per length)."""
        n = cfg.episode.samples
        if self.samples != n:
            reason = self.set_parameters(self.plant_params, [Parameter("samples", value=n)], self.plant_name)
            if reason:
                raise HasControlError(f"{self.plant_name} rejected samples = {n}: {reason}")
            self.samples = n

    def run(self, gains, cfg, bag: Path, timeout: float, writer=None, prefix: str = "") -> tuple | None:
        """One episode with ``gains`` recorded to ``bag``, and its (J, e_max, e_μ, e_σ)
        from the bag (+inf each when it cannot be scored); recorded into ``writer``
        (another bag, still open) instead: None, the caller scores it once that bag is closed."""
        self.prepare(cfg)
        reason = self.set_gains(gains)
        if reason is not None:
            self.logger.warning(f"{self.controller_name} rejected k = {tuple(gains)}: {reason}; scored +inf")
            return UNSCORED
        self._trigger(self.plant_reset)
        self._trigger(self.controller_reset)
        n = cfg.episode.samples
        self.recorder.open(bag, cfg, samples=n, writer=writer, prefix=prefix)
        self._trigger(self.plant_start)
        finished = self.recorder.done.wait(timeout)
        end = time.monotonic() + 2.0               # the last sample's reference and internals
        while finished and not self.recorder.diverged and time.monotonic() < end and not all(
                self.recorder.count(t) >= n for t in ("state", "controller/reference")):
            time.sleep(0.001)
        if writer is not None:
            self.recorder.detach()
            return None                             # scored by the caller once the bag is closed
        self.recorder.close()
        if not finished:
            self._trigger(self.plant_reset)
            self.logger.warning(f"{self.namespace}: episode with k = {tuple(gains)} did not finish "
                                f"within {timeout:g} s; scored +inf")
            return UNSCORED
        try:
            score, _ = score_bag(bag, on_warning=self.logger.warning)
        except BagError as exc:
            self.logger.warning(f"{exc}; scored +inf")
            return UNSCORED
        return (score.J, score.e_max, score.e_mu, score.e_sigma)


def _python(value):
    """A ParameterValue as plain Python (arrays as lists), for JSON."""
    v = parameter_value_to_python(value)
    return v.tolist() if hasattr(v, "tolist") else (list(v) if isinstance(v, (list, tuple)) else v)
