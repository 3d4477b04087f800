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
The bookkeeping of the changes asked and the report are ROS-free
(:mod:`has_control.deploy.report`); the node wires the topics and the parameters.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from has_control.config import build_config, config_parameters, with_horizon
from has_control.core.cost import score_arrays
from has_control.core.episode import Col, simulate
from has_control.core.params import Config
from has_control.deploy.guarded import DeploymentPlan
from has_control.deploy.report import Changes, NodeDeployment
from has_control.deploy.stepping import Deployer
from has_control.deploy.watchdog import WatchdogLimits
from has_control.deploy.watched import Pairing, Watched, gains_of, internals_of
from has_control.wire.codec import float64_array_layout
from has_control.wire.topics import FLOAT64_ARRAY, JOINT_STATE
from has_control.nodes.controller_node import ControllerNode
from has_control.nodes.plant_node import PREFIXES as PLANT_PREFIXES, PlantNode
from has_control.nodes.recorder import Recorder

#: The watchdog's series in the bag: (t [s], u [m], e1 [m], trip reason (0: none)).
WATCHDOG_TOPIC = "deploy/watchdog"
WATCHDOG_COLUMNS = ("t", "u", "e1", "reason")
_CLASSES = {JOINT_STATE: JointState, FLOAT64_ARRAY: Float64MultiArray}


def _qos(latched: bool = False) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


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
        self.changes = Changes(self.schedule)      # asked, and when each took effect
        topic, ty = watched.command
        self.recorder = None
        if record is not None:
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
        self.gains_seen.append(got)
        self.changes.announced(*got)

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
        self.changes.ask(i, row, why)

        def answered(f, row=row) -> None:
            r = f.result().result if f.result() is not None else None
            if r is not None and not r.successful:
                self.refused.append(f"row {row}: {r.reason}")
                self.get_logger().error(f"{self.watched.controller} refused gains {tuple(k)}: {r.reason}")
        future.add_done_callback(answered)

    def _finish(self) -> None:
        """The plan has run: the report (and the bag)."""
        self.done = True
        self.result.take(self.deployer, self.schedule, self.cfg.episode.as_array(), self.changes)

    def close(self) -> NodeDeployment:
        """Take what the gains topic said, write the bag; the report."""
        res = self.result
        res.changes = self.changes.rows()
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
