"""A guarded deployment on a running machine, through ROS: a node that moves a
running controller node from its safe gains to the tuned ones by setting its
``gains.k1..k3`` parameters (``set_parameters_atomically``), in the steps of a
:class:`~has_control.deploy.guarded.DeploymentPlan`, while the watchdog
(:mod:`has_control.deploy.watchdog`, through the one stepping policy of
:mod:`has_control.deploy.stepping`) watches the topics the loop publishes
(:mod:`has_control.deploy.watched`: the has_control layout or the ros2_control
one), and falls back to the last gains that held a whole step when it trips.

Time is the loop's: each sample's t from the controller's internals, so a
lock-step simulated machine and a real one are judged alike. When a change
takes effect is read from the controller's ``~/gains`` topic (published when
new gains take effect), so the report gives the fallback's latency in
samples, from the sample that tripped to the first sample run on the fallback
gains. The run (the watched topics and the watchdog's series, topic
``deploy/watchdog`` [t, u, e1, reason]) is recorded to a bag when asked.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from has_control.core.cost import score_arrays
from has_control.core.episode import Col, simulate
from has_control.core.params import Config
from has_control.deploy.guarded import DeploymentPlan, gap_words
from has_control.deploy.stepping import Comparison, Deployer
from has_control.deploy.watchdog import WatchdogLimits
from has_control.deploy.watched import Pairing, Watched, gains_of, internals_of
from has_control.wire.codec import float64_array_layout
from has_control.wire.topics import FLOAT64_ARRAY, JOINT_STATE

#: The watchdog's series in the bag: (t [s], u [m], e1 [m], trip reason (0: none)).
WATCHDOG_TOPIC = "deploy/watchdog"
WATCHDOG_COLUMNS = ("t", "u", "e1", "reason")
_CLASSES = {JOINT_STATE: JointState, FLOAT64_ARRAY: Float64MultiArray}


def _qos(latched: bool = False) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


@dataclass
class NodeDeployment:
    """What a deployment through the topics did. Samples are the loop's;
    ``changes``: (sample asked, row, why, sample it took effect or None)."""

    plan: DeploymentPlan
    step: float
    changes: list = field(default_factory=list)
    tripped: tuple | None = None              # (sample, reason, step)
    second_trip: int | None = None
    first: int | None = None
    last: int | None = None
    J: float = math.nan                        # of the samples watched
    safe_J: float | None = None                # the safe gains alone over the same run (a simulated machine)
    tuned_rate: float | None = None            # J per second on the final gains' step (no trip)
    predicted_J: float | None = None
    predicted_horizon: float | None = None
    final_gains: tuple = ()
    bag: Path | None = None
    comparison: Comparison | None = None       # what the plan's final comparison measured and kept
    hf_limit: float | None = None              # the watchdog's command-power limit in effect [m]

    def fallback_latency(self) -> float | None:
        """Seconds of the loop from the sample that tripped to the first sample on the fallback gains."""
        if self.tripped is None:
            return None
        for asked, _row, why, took in self.changes:
            if why.startswith("fallback") and took is not None:
                return (took - self.tripped[0]) * self.step
        return None

    @property
    def gap(self) -> float | None:
        """Measured over predicted J of the tuned gains: the tuned gains' mean cost rate on
        the machine (their step, when no trip) against the prediction's over its horizon."""
        if self.tuned_rate is None or not self.predicted_J or not self.predicted_horizon:
            return None
        return self.tuned_rate / (self.predicted_J / self.predicted_horizon)

    def lines(self) -> list[str]:
        n = (self.last - self.first + 1) if self.first is not None else 0
        out = [f"deployed through the controller's parameters in {self.plan.steps} steps of {self.plan.hold:g} s "
               f"after {self.plan.settle:g} s: {n} samples watched, J = {self.J:.6e}"
               + (f" (safe gains alone {self.safe_J:.6e}, {self.J / self.safe_J:.3g}x)" if self.safe_J else "")]
        for asked, row, why, took in self.changes:
            when = f"took effect at sample {took} (+{took - asked})" if took is not None else "not seen taking effect"
            out.append(f"  sample {asked}: row {row} ({why}), {when}")
        if self.tripped is None:
            out.append(f"watchdog: no trip; final gains ({', '.join(f'{k:.2f}' for k in self.final_gains)})")
        else:
            lat = self.fallback_latency()
            out.append(f"watchdog: TRIPPED at t = {self.tripped[0] * self.step:.4f} s on step {self.tripped[2]} "
                       f"({self.tripped[1]}); fallback in effect "
                       + (f"{lat * 1e3:.1f} ms later" if lat is not None else "not seen")
                       + f"; final gains ({', '.join(f'{k:.2f}' for k in self.final_gains)})")
        if self.comparison is not None:
            out.append(self.comparison.line(self.plan.steps))
        g = self.gap
        if g is not None:
            out.append(f"measured against predicted J: {g:.3g}x ({gap_words(g)}; "
                       f"the tuned gains' cost rate over their step against the prediction's over "
                       f"{self.predicted_horizon:g} s)")
        elif self.predicted_J is not None:
            out.append("measured against predicted J: not measured (the tuned gains did not hold their step)")
        if self.bag is not None:
            out.append(f"wrote {self.bag}")
        return out

    def as_json(self) -> dict:
        f = lambda v: v if v is None or math.isfinite(v) else None  # noqa: E731
        return {"J": f(self.J), "safe_J": self.safe_J,
                "samples": (self.last - self.first + 1) if self.first is not None else 0,
                "tripped": self.tripped is not None,
                "tripped_at": self.tripped[0] * self.step if self.tripped else None,
                "reason": self.tripped[1] if self.tripped else None, "step": self.tripped[2] if self.tripped else None,
                "second_trip_at": self.second_trip * self.step if self.second_trip is not None else None,
                "fallback_latency": self.fallback_latency(), "final_gains": list(self.final_gains),
                "changes": [{"sample": a, "row": r, "why": w, "took_effect": t} for a, r, w, t in self.changes],
                "predicted_J": self.predicted_J, "gap": f(self.gap) if self.gap is not None else None,
                "gap_over_2x": bool(self.gap is not None and self.gap > 2.0),
                "comparison": self.comparison.as_json() if self.comparison is not None else None,
                "hf_limit": self.hf_limit, "bag": str(self.bag) if self.bag else None}


class DeployNode(Node):
    """Deploys ``plan`` to the controller of ``watched`` (see the module);
    ``cfg``: the controller's configuration (its ``simulation.step`` and the
    cost's λ's; the bag's parameters). :meth:`start` once the controller's
    parameter services are ready; :attr:`done` when the plan has run."""

    def __init__(self, plan: DeploymentPlan, limits: WatchdogLimits, cfg: Config, watched: Watched,
                 record: str | Path | None = None, predicted_J: float | None = None,
                 predicted_horizon: float | None = None, name: str = "deploy", **kwargs):
        super().__init__(name, **kwargs)
        plan.check()
        watched.check()
        self.plan, self.cfg, self.watched = plan, cfg, watched
        self.dt = cfg.episode.step
        self.step_ns = int(round(self.dt * 1e9))
        self.schedule = plan.schedule()
        self.deployer = Deployer(self.schedule, plan.switches(self.dt), limits, self.dt,
                                 end=int(round(plan.duration() / self.dt)), compare=plan.compare(self.dt),
                                 ep=cfg.episode.as_array())
        self.pairing = Pairing(stamped=watched.layout == "has_control")
        self.params = AsyncParameterClient(self, watched.controller)
        self.result = NodeDeployment(plan, self.dt, predicted_J=predicted_J, predicted_horizon=predicted_horizon)
        self.started = False
        self.done = False
        self.refused: list[str] = []
        self.gains_seen: list[tuple[int, tuple]] = []
        self._asked: list[list] = []               # [sample asked, row, why, took effect]
        topic, ty = watched.command
        self.recorder = None
        if record is not None:
            # lazy: the bag writer only when recording
            from has_control.nodes.recorder import Recorder
            rec_topics = {watched.internals.lstrip("/"): FLOAT64_ARRAY, watched.gains.lstrip("/"): FLOAT64_ARRAY}
            if watched.layout == "has_control":   # a stamped command: its log time is the sample's
                rec_topics[topic.lstrip("/")] = JOINT_STATE
            self.recorder = Recorder(self, "", topics=rec_topics)
            self.recorder.open(record, cfg)
            self._record_path = Path(record)
        self.create_subscription(_CLASSES[ty], topic, self._on_command, _qos(), raw=True)
        self.create_subscription(Float64MultiArray, watched.internals, self._on_internals, _qos(), raw=True)
        self.create_subscription(Float64MultiArray, watched.gains, self._on_gains, _qos(latched=True), raw=True)

    # --- set-up --------------------------------------------------------------
    def ready(self) -> bool:
        return self.params.services_are_ready()

    def start(self) -> None:
        """Ask for the controller's internals (the watchdog's e1); the plan starts at the next sample seen."""
        self.params.set_parameters([Parameter("publish_internals", value=True)])
        self.started = True

    # --- what the loop publishes ---------------------------------------------
    def _on_command(self, data: bytes) -> None:
        got = self.watched.command_of(data, self.step_ns)
        if got is not None and self.started:
            for triple in self.pairing.command(*got):
                self._sample(*triple)

    def _on_internals(self, data: bytes) -> None:
        got = internals_of(data, self.dt)
        if got is not None and self.started:
            for triple in self.pairing.internals(*got):
                self._sample(*triple)

    def _on_gains(self, data: bytes) -> None:
        got = gains_of(data, self.dt)
        if got is None:
            return
        i, k = got
        self.gains_seen.append((i, k))
        for entry in self._asked:                   # the first announcement of the gains asked for
            same = all(math.isclose(a, b, rel_tol=1e-9) for a, b in zip(k, self.schedule[entry[1]]))
            if entry[3] is None and entry[0] <= i and same:
                entry[3] = i

    def _sample(self, i: int, u: float, e1: float) -> None:
        if self.done:
            return
        row = self.deployer.sample(i, u, e1)
        if row >= 0:
            self._set(i, row, self.deployer.rows[-1][2])
        if self.deployer.done():
            self._finish()

    def _set(self, i: int, row: int, why: str) -> None:
        k = self.schedule[row]
        future = self.params.set_parameters_atomically(
            [Parameter(f"gains.k{j + 1}", value=float(k[j])) for j in range(3)])
        self._asked.append([i, row, why, None])

        def answered(f, row=row) -> None:
            r = f.result().result if f.result() is not None else None
            if r is not None and not r.successful:
                self.refused.append(f"row {row}: {r.reason}")
                self.get_logger().error(f"{self.watched.controller} refused gains {tuple(k)}: {r.reason}")
        future.add_done_callback(answered)

    def _finish(self) -> None:
        """The plan has run: the report (and the bag)."""
        self.done = True
        d, res = self.deployer, self.result
        res.first, res.last = d.first, d.last
        res.tripped, res.second_trip = d.tripped(), d.second_trip()
        ep = self.cfg.episode.as_array()
        res.J = d.cost(ep)
        res.final_gains = tuple(float(v) for v in self.schedule[d.final_row()])
        res.comparison = d.comparison()
        res.hf_limit = float(d.lim[2])
        steps = [k for k, e in enumerate(self._asked) if e[2] == "step"]
        if res.tripped is None and steps:             # the tuned gains' step, up to the next change (if any)
            k = steps[-1]
            since = self._asked[k][3] if self._asked[k][3] is not None else self._asked[k][0]
            until = self._asked[k + 1][0] if k + 1 < len(self._asked) else d.last + 1
            if until > since:
                res.tuned_rate = d.cost(ep, since=since, until=until) / ((until - since) * self.dt)

    def close(self) -> NodeDeployment:
        """Take what the gains topic said, write the bag; the report."""
        res = self.result
        res.changes = [tuple(e) for e in self._asked]
        if self.recorder is not None:
            layout = float64_array_layout(WATCHDOG_COLUMNS)
            self.recorder.add(WATCHDOG_TOPIC, FLOAT64_ARRAY, [layout.encode(row) for row in self.deployer.series])
            res.bag = self.recorder.close()
            self.recorder = None
        return res


def deploy_on_running_machine(plan: DeploymentPlan, limits: WatchdogLimits, cfg: Config, watched: Watched,
                              executor, node_kwargs: dict, record=None, predicted_J=None, predicted_horizon=None,
                              timeout: float = 60.0, spin=None) -> NodeDeployment:
    """Run a :class:`DeployNode` on ``executor`` (which the caller owns and may
    share with the machine's nodes) until the plan has run; ``spin()``: one
    turn of the executor (default ``executor.spin_once(timeout_sec=0.01)``)."""
    node = DeployNode(plan, limits, cfg, watched, record, predicted_J, predicted_horizon, **node_kwargs)
    executor.add_node(node)
    spin = spin or (lambda: executor.spin_once(timeout_sec=0.01))
    end = time.monotonic() + timeout
    try:
        while not node.ready():
            if time.monotonic() > end:
                raise TimeoutError(f"{watched.controller}: its parameter services did not appear")
            spin()
        node.start()
        while not node.done:
            if time.monotonic() > end:
                raise TimeoutError(f"the plan did not run within {timeout:g} s (is the loop running?)")
            spin()
        for _ in range(20):                          # the last change's announcement
            spin()
        return node.close()
    finally:
        executor.remove_node(node)
        node.destroy_node()


def deploy_on_plant_node(cfg: Config, plan: DeploymentPlan, limits: WatchdogLimits | None = None, *, context,
                         record=None, predicted_J=None, timeout: float = 600.0):
    """The project's plant node (``cfg``'s ``plant.*``, lock-step) and controller node
    (``cfg`` with the plan's safe gains; an episode of the plan's duration + 50 ms) composed in this process with a
    :class:`DeployNode` on one executor: the deployment through the topics and
    the controller's parameters as against any running machine. Returns (the
    :class:`NodeDeployment`, the controller's trace of the run (TRACE_COLUMNS))."""
    # lazy: the plant and controller nodes load the loop's compiled steps; only this composition needs them
    from rclpy.experimental import EventsExecutor
    from has_control.config import build_config, config_parameters, with_horizon
    from has_control.nodes.controller_node import ControllerNode
    from has_control.nodes.plant_node import PREFIXES as PLANT_PREFIXES, PlantNode
    predicted_horizon = cfg.episode.horizon                       # what a prediction on ``cfg`` ran over
    cfg = with_horizon(cfg, max(plan.duration() + 0.05, 1.5))    # the plan, and a little to see its end
    cfg = build_config({f"gains.k{j + 1}": float(plan.safe[j]) for j in range(3)}, source="the safe gains", base=cfg)
    limits = limits or WatchdogLimits(valve_limit=cfg.plant.valve_limit)
    params = [Parameter(k, value=v) for k, v in config_parameters(cfg).items()]
    n = cfg.episode.samples
    plant = PlantNode(context=context, parameter_overrides=[p for p in params if p.name.startswith(PLANT_PREFIXES)]
                      + [Parameter("samples", value=n)])
    controller = ControllerNode(context=context, parameter_overrides=params)
    controller.quiet = True
    controller.record_trace(n)
    node = DeployNode(plan, limits, cfg, Watched(), record, predicted_J, predicted_horizon, context=context)
    executor = EventsExecutor(context=context)
    for x in (plant, controller, node):
        executor.add_node(x)
    try:
        end = time.monotonic() + 30.0
        while not (node.ready() and plant.state_pub.get_subscription_count()
                   and controller.command_pub.get_subscription_count() and node.count_publishers(
                       Watched().internals) and node.count_publishers(Watched().command[0])):
            if time.monotonic() > end:
                raise TimeoutError("plant, controller and deploy node did not discover each other in 30 s")
            executor.spin_once(timeout_sec=0.01)
        node.start()
        for _ in range(20):
            executor.spin_once(timeout_sec=0.005)
        plant.start()
        plant.run(executor)
        for _ in range(50):
            executor.spin_once(timeout_sec=0.002)
        res, trace = node.close(), controller.trace.copy()
        ep = cfg.episode.as_array()
        res.J = score_arrays(trace[:, Col.e1], trace[:, Col.u], ep, diverged=bool(np.isnan(trace[:, Col.u]).any())).J
        res.safe_J = simulate(cfg, plan.safe).score.J
        return res, trace
    finally:
        executor.shutdown()
        for x in (node, controller, plant):
            x.destroy_node()


__all__ = ["DeployNode", "NodeDeployment", "deploy_on_running_machine", "deploy_on_plant_node", "WATCHDOG_TOPIC"]
