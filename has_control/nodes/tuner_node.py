"""The tuner node: tunes the controller's gains (``swarm.variant``: cma-restarts,
the default, or the paper's particle swarms) and reports the bound diagnostics.

It drives the optimiser's ask/tell interface (:func:`has_control.tuning.tuner.tune`,
the same code as ``has-control tune``). With ``evaluator: graph`` every
candidate runs through the node graph: the tuner sets the controller's
gains with ``set_parameters_atomically``, resets plant and controller
(``~/reset``), starts the plant (``~/start``), records the episode to an
MCAP bag and takes the candidate's J from that bag. Several plant/controller
pairs in their own namespaces (``lanes: [/sim0, /sim1]``) evaluate
candidates in parallel, in this process or anywhere on the ROS network.
With ``evaluator: batch`` the candidates are scored by the in-process batch
evaluator (fast); either way the best gains are then set on every lane's
controller, and ``validate_best`` re-runs them through the graph, recorded
and scored from the bag.

Parameters: ``swarm.*`` and ``restarts.*`` (config/tuner.yaml), the model and episode
(``actuator.*``, ``simulation.*``, ``cost.*``, ``metrics.*``, ...; the same
files as plant and controller) and the world the batch evaluator simulates
and the bags record (``plant.*``, ``noise.*``, as plant and controller take
them), ``evaluator`` (graph | batch), ``validate_best``, ``scenarios`` (robust
tuning: a scenario file, scored with the batch evaluator; empty: the nominal
episode) and ``aggregate`` (mean | max | cvar:α),
``lanes`` (namespaces; ``[""]`` is the root), ``controller``
and ``plant`` (node names within a lane), ``record`` (a directory: the
session bag ``record/session``, the best gains as a ``--params-file``
``record/gains.yaml`` and, for graph evaluation, one bag per episode under
``record/episodes``; empty: episodes go to a temporary
directory), ``resume`` (a directory of an interrupted session),
``episode_timeout`` [s of wall time], ``log_every`` (log every n-th iteration),
``force`` (``record``: replace a session there), ``validation_tolerance``
(the graph's J of the best gains against the library's, relative). Every
parameter is described, checked and declared from a table
(:data:`TUNER_TABLE`: the model's, the tuning's and the tuner's own); a change
is checked when set, with the CLI's checks, and refused with the reason (the
old value stays); an accepted one takes effect at the next ``~/start``, which
reads the parameters again and refuses a known conflict at once (a session
in ``record`` without ``force``, nothing to ``resume``). ``lanes``,
``controller``, ``plant`` and ``autostart`` are read-only. Before the
validation the lanes' parameters are read back and stored in the session bag
(``/tuner/lanes``); a graph J that differs from the library's beyond the
tolerance is a warning, ``agrees: false`` in the result's ``validation`` block
(``tune.json``, ``~/status``) and a ``disagrees`` status (docs/nodes.md).
Topic ``~/progress`` (std_msgs/Float64MultiArray, its dimension labelled
with the columns of :data:`has_control.wire.topics.PROGRESS_COLUMNS`):
[iteration, best J, k1, k2, k3 [1/s], evaluations, elapsed [s], ETA [s]],
once per iteration.

The node is wiring (the parameters, the services, ``~/progress``, the lanes)
over ROS-free modules: the settings checks
(:mod:`has_control.tuning.service_settings`), the session service with its
status and result (:mod:`has_control.tuning.service`), the session over the
lanes (:mod:`has_control.tuning.lane_session`) and the graph evaluator
(:mod:`has_control.tuning.graph_evaluator`).
"""
from __future__ import annotations

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from has_control.common.errors import HasControlError
from has_control.tuning.parameters import TUNING_TABLE
from has_control.tuning.lane_session import OPTIONAL_LANES_WAIT, Cancelled
from has_control.tuning.service import TunerService
from has_control.tuning.service_settings import (EVALUATORS, OWN_PARAMETERS, PREFIXES, TUNER_TABLE, Settings,
                                                 settings_from)
from has_control.tuning.tuner import load_tuning, tuning_parameters
from has_control.nodes.parameters import (check_changes, config_from_node, declare_config, declare_plant_overrides,
                                          declare_table, plain)
from has_control.nodes.lanes import Lane
from has_control.wire.topics import PROGRESS_LAYOUT
from has_control.nodes.runtime import node_main, spin

__all__ = ["TunerNode", "read_settings", "main", "Cancelled", "Settings", "EVALUATORS", "OWN_PARAMETERS",
           "PREFIXES", "TUNER_TABLE", "OPTIONAL_LANES_WAIT"]


class TunerNode(Node):
    """The tuner's parameters, services and ``~/progress`` over a
    :class:`~has_control.tuning.service.TunerService` (the session, its status and result)."""

    def __init__(self, name: str = "tuner", **kwargs):
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES)
        declare_plant_overrides(self)                 # plant.mass etc.: the plant's, as the plant node has them
        declare_table(self, TUNING_TABLE.values(), tuning_parameters(load_tuning()))
        declare_table(self, OWN_PARAMETERS.values())
        settings = self.read_settings()               # bad start-up parameters: one ConfigError line
        lanes = list(self.get_parameter("lanes").value) or [""]
        self.lanes = [Lane(self, ns, self.get_parameter("controller").value,
                           self.get_parameter("plant").value, settings.cfg.episode.y_limit) for ns in lanes]
        self.progress_pub = self.create_publisher(Float64MultiArray, "~/progress", 10)
        self.service = TunerService(settings, self.lanes, self.get_logger(),
                                    lambda row: self.progress_pub.publish(PROGRESS_LAYOUT.encode(row)))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/cancel", self._on_cancel)
        self.create_service(Trigger, "~/status", self._on_status)

    # what the service holds: the settings of the last (or next) session, its status and result
    settings = property(lambda self: self.service.settings)
    cfg = property(lambda self: self.settings.cfg)
    status = property(lambda self: self.service.status)
    result = property(lambda self: self.service.result)
    error = property(lambda self: self.service.error)
    done = property(lambda self: self.service.done)

    # --- parameters: checked when set, read at ~/start ---------------------------
    def read_settings(self, changes: dict | None = None) -> Settings:
        """The session's settings from the parameters (with ``changes`` over them): :func:`read_settings`."""
        return read_settings(self, changes)

    def _on_set_parameters(self, params) -> SetParametersResult:
        """A change is checked now, with every other parameter (refused with the reason,
        the old value kept); an accepted one takes effect at the next ``~/start``."""
        reason = check_changes(TUNER_TABLE, params)
        if reason is None:
            try:
                self.read_settings({p.name: p.value for p in params})
            except HasControlError as exc:
                reason = str(exc)
        if reason is not None:
            self.get_logger().warning(f"rejected {sorted(p.name for p in params)}: {reason}")
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    # --- services ------------------------------------------------------------
    def start(self) -> str | None:
        """Start a session with the parameters as they are now (:meth:`TunerService.start`);
        the reason it refused, or None."""
        return self.service.start(self.read_settings)

    def _on_start(self, request, response):
        reason = self.start()
        response.success = reason is None
        response.message = "session started" if reason is None else reason
        return response

    def _on_cancel(self, request, response):
        response.success, response.message = self.service.cancel()
        return response

    def _on_status(self, request, response):
        """The status line; after a validated session, a second line ``validation: {JSON}``."""
        response.success = True
        response.message = self.service.status_message()
        return response


def read_settings(node: Node, changes: dict | None = None) -> Settings:
    """The session's settings from the parameters (with ``changes`` over them),
    through the checks ``has-control tune`` makes
    (:func:`~has_control.tuning.service_settings.settings_from`); a ConfigError line names the culprit."""
    changes = {k: plain(v) for k, v in (changes or {}).items()}

    def value(name):
        return changes[name] if name in changes else plain(node.get_parameter(name).value)
    return settings_from(value, lambda: config_from_node(
        node, PREFIXES, overrides={k: v for k, v in changes.items() if k.startswith(PREFIXES)}),
        f"parameter of {node.get_fully_qualified_name()}")


def main(args=None):
    failed = []

    def serve(executor, node: TunerNode) -> None:
        if node.get_parameter("autostart").value:
            if node.start() is not None:
                failed.append(True)
                return
            node.get_logger().info("ready: tuning (~/cancel stops it, ~/status tells)")
            spin(executor, done=node.done.is_set)
            failed.append(bool(node.error))
        else:
            node.get_logger().info("ready: call ~/start to tune (~/cancel, ~/status)")
            spin(executor)
    node_main(args, TunerNode, serve)
    if any(failed):
        raise SystemExit(2)
