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
"""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import tempfile
import threading
import time
from pathlib import Path

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from has_control.bag import score_bag
from has_control.common.errors import ConfigError, HasControlError
from has_control.config import CONFIG_TABLE, Param, config_parameters, refusal, table
from has_control.core.episode import simulate
from has_control.tuning.parameters import TUNING_TABLE
from has_control.tuning.tuner import Tuning, load_tuning, robust_tuning, tuning_from_parameters, tuning_parameters
from has_control.nodes.parameters import (check_changes, config_from_node, declare_config, declare_plant_overrides,
                                          declare_table, plain)
from has_control.nodes.lanes import GraphEvaluator, Lane
from has_control.wire.topics import PROGRESS_LAYOUT
from has_control.nodes.runtime import node_main, spin
from has_control.tuning.session import conflict, rewrite_result, run_session, write_lanes
from has_control.tuning.validation import (VALIDATION_TOLERANCE, disagreement_status, lane_differences,
                                           validation_block, validation_line)

PREFIXES = ("actuator.", "simulation.", "gains.", "adaptation.", "reference.", "cost.", "metrics.", "plant.", "noise.")
EVALUATORS = ("graph", "batch")
#: With evaluator batch, how long to look for the (optional) lanes once the tuning is done [s].
OPTIONAL_LANES_WAIT = 2.0
#: The tuner's own parameters (its table; the model's and the tuning's are CONFIG_TABLE's and TUNING_TABLE's).
OWN_PARAMETERS = table((
    Param("scenarios", "str", "", text="robust tuning: a scenario file scored by the batch evaluator "
          "(empty: the nominal episode)"),
    Param("aggregate", "str", "mean", text="robust tuning: mean | max | cvar:alpha of the scenarios' J"),
    Param("evaluator", "str", "batch", text="batch (in-process, fast) | graph (every candidate through the "
          "lanes' nodes)", choices=EVALUATORS),
    Param("validate_best", "bool", True, text="re-run the best gains through the graph, recorded and scored "
          "from the bag"),
    Param("validation_tolerance", "double", VALIDATION_TOLERANCE, text="the graph's J of the best gains may "
          "differ from the library's by this share of it; more is a disagreement", lower=0.0),
    Param("lanes", "str[]", [""], text="namespaces of the plant/controller pairs ('' is the root)", read_only=True),
    Param("controller", "str", "controller", text="the controller's node name within a lane", read_only=True),
    Param("plant", "str", "plant", text="the plant's node name within a lane", read_only=True),
    Param("record", "str", "", text="a directory: the session bag, gains.yaml and (graph) one bag per episode; "
          "empty: none kept"),
    Param("force", "bool", False, text="record: replace a session the directory holds (else ~/start "
          "refuses)"),
    Param("resume", "str", "", text="a directory of an interrupted session to resume"),
    Param("episode_timeout", "double", 120.0, "s of wall time", "graph: an episode not finished after this long "
          "scores +inf", lower=0.0, lower_open=True),
    Param("log_every", "int", 1, text="log every n-th iteration", lower=1),
    Param("keep_episodes", "bool", False, text="graph: keep one bag per episode under record/episodes (default: "
          "scored, then deleted)"),
    Param("autostart", "bool", True, text="tune at start-up and exit when done (false: wait for ~/start, serve "
          "until shut down)", read_only=True),
    Param("lane_timeout", "double", 30.0, "s", "graph: wait this long for the lanes' plant and controller; with "
          "evaluator batch they are optional (looked for once the tuning is done, the best gains set on them if "
          "found)", lower=0.0, lower_open=True),
))
#: Every parameter the tuner takes, by name.
TUNER_TABLE = {**{k: p for k, p in CONFIG_TABLE.items() if k.startswith(PREFIXES)}, **TUNING_TABLE,
               **OWN_PARAMETERS}
#: Bytes a recorded episode takes per sample (state, command, clock, reference, internals, each with
#: its MCAP record header): the estimate logged before a graph tuning.
BAG_BYTES_PER_SAMPLE = 246


class Cancelled(Exception):
    """``~/cancel`` was called: the session stops at the next episode or iteration."""


@dataclasses.dataclass(frozen=True)
class Settings:
    """What one session runs with: the parameters as they were at ``~/start``, validated."""

    cfg: object
    tuning: Tuning
    evaluator: str
    record: str | None
    resume: str | None
    force: bool
    episode_timeout: float
    validate: bool
    tolerance: float
    keep_episodes: bool
    log_every: int
    lane_timeout: float


class _Progress:
    """The session's observer: each iteration on ``~/progress``, in ``status`` and
    (every ``every``-th and the last) in the log; a cancel is raised here."""

    def __init__(self, node: "TunerNode", every: int):
        self.node, self.every, self.t0 = node, max(1, every), time.perf_counter()

    def __call__(self, sw) -> None:
        node, k = self.node, sw.best_x
        elapsed = time.perf_counter() - self.t0
        progress = sw.progress()                   # the share of the budget used, 0..1
        eta = elapsed / progress * (1.0 - progress) if progress > 0 else math.inf
        node.status = (f"running: {sw.name} iteration {sw.iteration} ({100 * progress:.0f} %), "
                       f"best J = {sw.best_f:.6e}, ETA {eta:.0f} s")
        node.progress_pub.publish(PROGRESS_LAYOUT.encode([
            float(sw.iteration), sw.best_f, *map(float, k), float(sw.evaluations), elapsed, eta]))
        if sw.iteration % self.every == 0 or sw.done:
            node.get_logger().info(
                f"{sw.name} iteration {sw.iteration} ({100 * progress:.0f} %): best J = {sw.best_f:.6e} "
                f"at k = ({k[0]:.2f}, {k[1]:.2f}, {k[2]:.2f}), {sw.evaluations} evaluations, ETA {eta:.0f} s")
        node._check_cancel()


class TunerNode(Node):
    def __init__(self, name: str = "tuner", **kwargs):
        super().__init__(name, **kwargs)
        declare_config(self, PREFIXES)
        declare_plant_overrides(self)                 # plant.mass etc.: the plant's, as the plant node has them
        declare_table(self, TUNING_TABLE.values(), tuning_parameters(load_tuning()))
        declare_table(self, OWN_PARAMETERS.values())
        self.settings = self.read_settings()          # bad start-up parameters: one ConfigError line
        lanes = list(self.get_parameter("lanes").value) or [""]
        self.lanes = [Lane(self, ns, self.get_parameter("controller").value,
                           self.get_parameter("plant").value, self.cfg.episode.y_limit) for ns in lanes]
        self.progress_pub = self.create_publisher(Float64MultiArray, "~/progress", 10)
        self.result: dict | None = None
        self.error: str | None = None
        self.done = threading.Event()
        self.done.set()                               # no session running
        self._thread: threading.Thread | None = None
        self._cancel = threading.Event()
        self.status = "idle: call ~/start"
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/cancel", self._on_cancel)
        self.create_service(Trigger, "~/status", self._on_status)

    # the settings of the last (or next) session
    cfg = property(lambda self: self.settings.cfg)
    tuning = property(lambda self: self.settings.tuning)
    evaluator = property(lambda self: self.settings.evaluator)
    lane_timeout = property(lambda self: self.settings.lane_timeout)

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
    def _on_start(self, request, response):
        reason = self.start()
        response.success = reason is None
        response.message = "session started" if reason is None else reason
        return response

    def _on_cancel(self, request, response):
        response.success = not self.done.is_set()
        response.message = "cancelling at the next episode" if response.success else f"nothing to cancel: {self.status}"
        if response.success:
            self._cancel.set()
        return response

    def _on_status(self, request, response):
        """The status line; after a validated session, a second line ``validation: {JSON}``."""
        response.success = True
        response.message = self.status
        validation = (self.result or {}).get("validation")
        if validation is not None and self.done.is_set():
            response.message += "\nvalidation: " + json.dumps(validation)
        return response

    def _check_cancel(self) -> None:
        if self._cancel.is_set():
            raise Cancelled()

    # --- session -------------------------------------------------------------
    def start(self) -> str | None:
        """Read and check the settings, refuse a known conflict (a session running, a
        session already in ``record`` without ``force``, nothing to ``resume``), then run
        the session in a thread of its own (the executor keeps spinning). The reason it
        refused, or None (also kept as ``error``)."""
        if not self.done.is_set():
            return f"busy: {self.status}"
        try:
            settings = self.read_settings()
            why = conflict(settings.record, settings.resume, settings.force)
            if why:
                raise HasControlError(f"parameter record/resume: {why}")
        except HasControlError as exc:
            self.error = str(exc)
            self.status = f"refused: {self.error}"
            self.get_logger().error(f"~/start refused: {self.error}")
            return self.error
        self.settings = settings
        self.done.clear()
        self._cancel.clear()
        self.result = self.error = None
        self.status = "running: starting"
        self._thread = threading.Thread(target=self._guarded, name="tuner-session", daemon=True)
        self._thread.start()
        return None

    def _guarded(self) -> None:
        try:
            self.result = self.run_session()
            gains = tuple(round(k, 2) for k in self.result["gains"])
            validation = self.result.get("validation") or {}
            if validation.get("agrees", True):
                self.status = f"finished: best k = {gains}, J = {self.result['J']}"
            else:
                self.status = disagreement_status(self.result["gains"], self.result["J"], validation)
        except Cancelled:
            self.status = "cancelled"
            self.get_logger().warning("session cancelled (~/cancel); a recorded one resumes with resume:=DIR")
        except HasControlError as exc:
            self.error = str(exc)
            self.status = f"failed: {self.error}"
            self.get_logger().error(self.error)
        except Exception as exc:                 # a bug, not bad input: keep its type in the report
            self.error = f"{type(exc).__name__}: {exc}"
            self.status = f"failed: {self.error}"
            self.get_logger().error(f"tuning session failed: {self.error}")
        finally:
            self.done.set()

    def wait_for_lanes(self, timeout: float | None = None, required: bool = True) -> bool:
        """Wait for every lane's plant and controller (bringing managed ones up);
        False if they are not all there in ``timeout`` and not ``required``."""
        timeout = self.lane_timeout if timeout is None else timeout
        end = time.monotonic() + timeout
        while not all(lane.ready() for lane in self.lanes):
            self._check_cancel()
            for lane in self.lanes:
                lane.bring_up()
            if time.monotonic() > end:
                if not required:
                    return False
                missing = [lane.namespace for lane in self.lanes if not lane.ready()]
                raise HasControlError(f"lanes {missing}: plant, controller (and their services) not found "
                                      f"within {timeout:g} s")
            time.sleep(0.01)
        return True

    def run_session(self) -> dict:
        """The session (the same runner as ``has-control tune``), candidates scored
        by the batch evaluator or through the lanes (:class:`~has_control.nodes.lanes.GraphEvaluator`),
        the best gains set on every lane and (``validate_best``) validated through the graph
        against the library's J of the same gains."""
        s, log = self.settings, self.get_logger()
        scratch = Path(tempfile.mkdtemp(prefix="has_control_tuner_"))
        graph = s.evaluator == "graph"
        lanes_up = self.wait_for_lanes(s.lane_timeout) if graph else None     # batch: looked for once tuned
        evaluator = None
        if graph:
            directory = s.resume or s.record
            keep = bool(directory) and s.keep_episodes
            episodes = Path(directory) / "episodes" if keep else scratch
            evaluator = GraphEvaluator(self.lanes, episodes, s.episode_timeout, keep, check=self._check_cancel,
                                       announce=lambda cfg: announce_graph(self, cfg, keep, episodes))
        found = {}

        def optional_lanes() -> bool:
            if "up" not in found:
                found["up"] = lanes_up if lanes_up is not None else self.wait_for_lanes(
                    min(OPTIONAL_LANES_WAIT, s.lane_timeout), required=False)
                if not found["up"]:
                    log.info("no plant/controller lanes found: the batch evaluator alone, validation in-process; "
                             "the best gains are set on no controller")
            return found["up"]

        def record_validation(gains, writer, cfg) -> bool:     # through the graph, into the session bag
            if not optional_lanes():
                return False                                    # the session records the in-process run
            found["parameters"] = self._lane_parameters()
            write_lanes(writer, found["parameters"])
            self.status = f"validating: k = {_k(gains)} through the graph (lane {self.lanes[0].namespace})"
            self.lanes[0].run(gains, cfg, writer.path, s.episode_timeout, writer=writer, prefix="/validation")
            return True

        try:
            run = run_session(s.cfg, s.tuning, s.record, resume_dir=s.resume, replace=s.force,
                              evaluator=s.evaluator, batch=evaluator, on_iteration=_Progress(self, s.log_every),
                              record_validation=record_validation if s.validate else None,
                              announce=log.info, on_warning=log.warning)
            res, out, best = run.result, dict(run.out), run.result.gains
            if res.bounds is not None:
                for check in res.bounds.checks:
                    log.info(f"bounds: {check.line()}")
                for warning in res.bounds.warnings:
                    log.warning(f"warning: {warning}")
            up = optional_lanes()
            out.update(evaluator=s.evaluator, lanes=[lane.namespace for lane in self.lanes] if up else [])
            if run.directory:
                out["gains_file"] = str(run.directory / "gains.yaml")
            if not up:
                if s.validate:
                    self.status = f"validating: k = {_k(best)} in-process"
                    validation = simulate(run.cfg, best).score
                    out["validation"] = validation.as_json()
                    out["validation_bag"] = None
                    log.info(f"validated k = {_k(best)} in-process: J = {validation.J:.6e}")
                out["controller_gains"] = None
                return self._finish(run, out)
            for lane in self.lanes:
                lane.prepare(run.cfg)
                reason = lane.set_gains(best)
                if reason:
                    raise HasControlError(f"{lane.controller_name} rejected the best gains {best}: {reason}")
            if s.validate:
                bag = run.bag
                if bag is None:
                    found["parameters"] = self._lane_parameters()
                    self.status = f"validating: k = {_k(best)} through the graph (lane {self.lanes[0].namespace})"
                    bag = scratch / "validation"
                    self.lanes[0].run(best, run.cfg, bag, s.episode_timeout)
                validation, _ = score_bag(bag, on_warning=log.warning)
                out["validation"] = self._compare(validation, run.cfg, best, found.get("parameters", []),
                                                  s.tolerance)
                out["validation_bag"] = str(bag) if run.bag else None
            out["controller_gains"] = self.lanes[0].gains()
            return self._finish(run, out)
        finally:
            if evaluator is not None:
                evaluator.close()
            shutil.rmtree(scratch, ignore_errors=True)

    def _finish(self, run, out: dict) -> dict:
        """The result, with its validation, also in ``tune.json`` when the session is recorded."""
        if run.directory is not None:
            rewrite_result(run.directory, out)
        return out

    def _lane_parameters(self) -> list[dict]:
        """Each lane's controller and plant parameters as they are (read back through their services)."""
        return [{"lane": lane.namespace, **lane.parameters()} for lane in self.lanes]

    def _compare(self, validation, cfg, best, lanes: list[dict], tolerance: float) -> dict:
        """The graph's validation against the library's J of the same gains on the tuner's
        model (:mod:`has_control.tuning.validation`), logged (a warning beyond ``tolerance``)."""
        block = validation_block(validation.as_json(), validation.J, simulate(cfg, best).score.J,
                                 lane_differences(config_parameters(cfg), lanes), tolerance)
        if block["agrees"]:                      # (rclpy: one severity per call site)
            self.get_logger().info(validation_line(block, best))
        else:
            self.get_logger().warning(validation_line(block, best))
        return block


def read_settings(node: Node, changes: dict | None = None) -> Settings:
    """The session's settings from the parameters (with ``changes`` over them),
    through the checks ``has-control tune`` makes; a ConfigError line names the culprit."""
    changes = {k: plain(v) for k, v in (changes or {}).items()}
    where = f"parameter of {node.get_fully_qualified_name()}"

    def value(name):
        return changes[name] if name in changes else plain(node.get_parameter(name).value)
    for name in OWN_PARAMETERS:
        reason = refusal(OWN_PARAMETERS, name, value(name))
        if reason is not None:
            raise ConfigError(f"{where}: {reason}")
    cfg = config_from_node(node, PREFIXES, overrides={k: v for k, v in changes.items() if k.startswith(PREFIXES)})
    flat = {k: value(k) for k in TUNING_TABLE}
    tuning = tuning_from_parameters(flat, {k: where for k in flat})
    evaluator = value("evaluator")
    path, how = value("scenarios"), value("aggregate")
    if path and evaluator == "graph":
        raise ConfigError(f"parameter scenarios = {path!r}: needs evaluator batch (the lanes run one plant)")
    # checked as tune's --scenarios/--aggregate; "mean" (the default) without scenarios is the nominal episode
    tuning = robust_tuning(tuning, cfg, path, how if path or how != "mean" else None,
                           ("parameter scenarios", "parameter aggregate"))
    return Settings(cfg, tuning, evaluator, value("record") or None, value("resume") or None,
                    bool(value("force")), float(value("episode_timeout")), bool(value("validate_best")),
                    float(value("validation_tolerance")), bool(value("keep_episodes")),
                    int(value("log_every")), float(value("lane_timeout")))


def announce_graph(node: "TunerNode", cfg, keep: bool, episodes: Path) -> None:
    """Before a graph tuning: how many episodes, how long (from a lock-step rate
    of 1 000–20 000 samples/s per lane), and what the bags take."""
    t = node.tuning.swarm
    count = t.particles * t.iterations
    samples = cfg.episode.samples
    lanes = len(node.lanes)
    per_bag = samples * BAG_BYTES_PER_SAMPLE
    fast, slow = (count * samples / lanes / rate for rate in (20_000.0, 1_000.0))
    node.get_logger().info(
        f"graph tuning: {count} episodes of {samples} samples over {lanes} lane(s), about "
        f"{_duration(fast)} to {_duration(slow)}; each episode's bag ~{per_bag / 1e6:.1f} MB, "
        + (f"kept under {episodes} ({count * per_bag / 1e9:.2f} GB in all)" if keep
           else "scored then deleted (keep_episodes:=true keeps them)") + "; ~/progress shows the ETA")


def _k(gains) -> str:
    return f"({gains[0]:.2f}, {gains[1]:.2f}, {gains[2]:.2f})"


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


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
