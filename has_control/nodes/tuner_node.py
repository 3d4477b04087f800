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
``episode_timeout`` [s of wall time], ``log_every`` (log every n-th iteration).
Topic ``~/progress`` (std_msgs/Float64MultiArray, its dimension labelled
with the columns of :data:`has_control.wire.topics.PROGRESS_COLUMNS`):
[iteration, best J, k1, k2, k3 [1/s], evaluations, elapsed [s], ETA [s]],
once per iteration.
"""
from __future__ import annotations

import math
import shutil
import tempfile
import threading
import time
from pathlib import Path

from rclpy.node import Node
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from rcl_interfaces.msg import ParameterDescriptor

from has_control.bag import score_bag
from has_control.common.errors import ConfigError, HasControlError
from has_control.core.episode import simulate
from has_control.tuning.tuner import Tuning, load_tuning, robust_tuning, tuning_from_parameters, tuning_parameters
from has_control.nodes.parameters import config_from_node, declare_config, declare_plant_overrides
from has_control.nodes.lanes import GraphEvaluator, Lane
from has_control.wire.topics import PROGRESS_LAYOUT
from has_control.nodes.runtime import node_main, spin
from has_control.tuning.session import run_session

PREFIXES = ("actuator.", "simulation.", "gains.", "adaptation.", "reference.", "cost.", "metrics.", "plant.", "noise.")
EVALUATORS = ("graph", "batch")
#: What each swarm.* parameter means (config/tuner.yaml; SPEC §7).
SWARM_PARAMETERS = {
    "swarm.variant": "pso | pso-cp | pso-cp-tvac (SPEC §7)",
    "swarm.seed": "seed of every random draw of the swarm",
    "swarm.particles": "N, particles per iteration",
    "swarm.iterations": "MAXITER, iterations",
    "swarm.target": "stop when the best J <= target",
    "swarm.lower": "x_min of (k1, k2, k3) [1/s]",
    "swarm.upper": "x_max of (k1, k2, k3) [1/s]",
    "swarm.velocity_limit": "v_max of a particle per iteration (v_min = -v_max) [1/s]",
    "swarm.inertia_max": "omega_max, inertia weight at the first iteration",
    "swarm.inertia_min": "omega_min, inertia weight at the last iteration",
    "swarm.c1": "cognitive acceleration c1 (PSO, PSO+CP)",
    "swarm.c2": "social acceleration c2 (PSO, PSO+CP)",
    "swarm.c1_start": "TVAC: c1 at the first iteration",
    "swarm.c1_end": "TVAC: c1 at the last iteration",
    "swarm.c2_start": "TVAC: c2 at the first iteration",
    "swarm.c2_end": "TVAC: c2 at the last iteration",
    "swarm.crazy_redraw": "positive: U(0, v_max) (paper Eq. 37) | symmetric: U(-v_max, v_max)",
    "swarm.crazy_probability": "exp-difference: w_min*exp(w - w_max) (SPEC) | exp-ratio: w_min*exp(-w/w_max)",
}
#: The tuner's own parameters: (name, default, meaning and unit).
OWN_PARAMETERS = (
    ("scenarios", "", "robust tuning: a scenario file scored by the batch evaluator (empty: the nominal episode)"),
    ("aggregate", "mean", "robust tuning: mean | max | cvar:alpha of the scenarios' J"),
    ("evaluator", "batch", "batch (in-process, fast) | graph (every candidate through the lanes' nodes)"),
    ("validate_best", True, "re-run the best gains through the graph, recorded and scored from the bag"),
    ("lanes", [""], "namespaces of the plant/controller pairs ('' is the root)"),
    ("controller", "controller", "the controller's node name within a lane"),
    ("plant", "plant", "the plant's node name within a lane"),
    ("record", "", "a directory: the session bag, gains.yaml and (graph) one bag per episode; empty: none kept"),
    ("resume", "", "a directory of an interrupted session to resume"),
    ("episode_timeout", 120.0, "graph: an episode not finished after this long scores +inf [s of wall time]"),
    ("log_every", 1, "log every n-th iteration"),
    ("keep_episodes", False, "graph: keep one bag per episode under record/episodes (default: scored, then deleted)"),
    ("autostart", True, "tune at start-up and exit when done (false: wait for ~/start, serve until shut down)"),
    ("lane_timeout", 30.0, "wait this long for the lanes' plant and controller [s]; with evaluator batch they "
     "are optional (the best gains are set on them if found)"),
)
#: Bytes a recorded episode takes per sample (state, command, clock, reference, internals, each with
#: its MCAP record header): the estimate logged before a graph tuning.
BAG_BYTES_PER_SAMPLE = 246


class Cancelled(Exception):
    """``~/cancel`` was called: the session stops at the next episode or iteration."""


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
        for key, value in tuning_parameters(load_tuning()).items():
            self.declare_parameter(key, value, ParameterDescriptor(description=SWARM_PARAMETERS.get(key, key)))
        for key, value, text in OWN_PARAMETERS:
            self.declare_parameter(key, value, ParameterDescriptor(description=text))
        self.cfg = config_from_node(self, PREFIXES)
        self.tuning = self._tuning()
        self.evaluator = self.get_parameter("evaluator").value
        if self.evaluator not in EVALUATORS:
            raise ConfigError(f"parameter evaluator = {self.evaluator!r}: expected one of {', '.join(EVALUATORS)}")
        self.tuning = self._robust(self.tuning)
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
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/cancel", self._on_cancel)
        self.create_service(Trigger, "~/status", self._on_status)

    def _on_start(self, request, response):
        response.success = self.done.is_set()
        response.message = "session started" if response.success else f"busy: {self.status}"
        if response.success:
            self.start()
        return response

    def _on_cancel(self, request, response):
        response.success = not self.done.is_set()
        response.message = "cancelling at the next episode" if response.success else f"nothing to cancel: {self.status}"
        if response.success:
            self._cancel.set()
        return response

    def _on_status(self, request, response):
        response.success = True
        response.message = self.status
        return response

    def _check_cancel(self) -> None:
        if self._cancel.is_set():
            raise Cancelled()

    @property
    def lane_timeout(self) -> float:
        return float(self.get_parameter("lane_timeout").value)

    def _tuning(self) -> Tuning:
        flat = {f"{prefix}.{k}": p.value for prefix in ("swarm", "restarts")
                for k, p in self.get_parameters_by_prefix(prefix).items()}
        flat = {k: (list(v) if hasattr(v, "tolist") or isinstance(v, (list, tuple)) else v) for k, v in flat.items()}
        return tuning_from_parameters(flat, {k: f"parameter {k} of {self.get_fully_qualified_name()}" for k in flat})

    def _robust(self, tuning: Tuning) -> Tuning:
        """``tuning`` scored on the scenarios of parameter ``scenarios`` (a file; empty: the nominal episode)."""
        path, how = self.get_parameter("scenarios").value, self.get_parameter("aggregate").value
        if path and self.evaluator == "graph":
            raise ConfigError(f"parameter scenarios = {path!r}: needs evaluator batch (the lanes run one plant)")
        # checked as tune's --scenarios/--aggregate; "mean" (the default) without scenarios is the nominal episode
        return robust_tuning(tuning, self.cfg, path, how if path or how != "mean" else None,
                             ("parameter scenarios", "parameter aggregate"))

    # --- session -------------------------------------------------------------
    def start(self) -> None:
        """Run the session in a thread of its own (the executor keeps spinning)."""
        self.done.clear()
        self._cancel.clear()
        self.result = self.error = None
        self.status = "running: starting"
        self._thread = threading.Thread(target=self._guarded, name="tuner-session", daemon=True)
        self._thread.start()

    def _guarded(self) -> None:
        try:
            self.result = self.run_session()
            self.status = f"finished: best k = {tuple(round(k, 2) for k in self.result['gains'])}, " \
                          f"J = {self.result['J']}"
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
        timeout = float(self.get_parameter("lane_timeout").value) if timeout is None else timeout
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
        the best gains set on every lane and (``validate_best``) validated through the graph."""
        log = self.get_logger()
        record = self.get_parameter("record").value or None
        resume_dir = self.get_parameter("resume").value or None
        timeout = float(self.get_parameter("episode_timeout").value)
        validate = bool(self.get_parameter("validate_best").value)
        scratch = Path(tempfile.mkdtemp(prefix="has_control_tuner_"))
        graph = self.evaluator == "graph"
        # with evaluator batch, lanes are optional
        lanes_up = self.wait_for_lanes(None if graph else min(5.0, self.lane_timeout), required=graph)
        if not lanes_up:
            log.info("no plant/controller lanes found: the batch evaluator alone, validation in-process; "
                     "the best gains are set on no controller")
        evaluator = None
        if graph:
            directory = resume_dir or record
            keep = bool(directory) and bool(self.get_parameter("keep_episodes").value)
            episodes = Path(directory) / "episodes" if keep else scratch
            evaluator = GraphEvaluator(self.lanes, episodes, timeout, keep, check=self._check_cancel,
                                       announce=lambda cfg: self._announce_graph(cfg, keep, episodes))

        def record_validation(gains, writer, cfg) -> None:     # through the graph, into the session bag
            self.lanes[0].run(gains, cfg, writer.path, timeout, writer=writer, prefix="/validation")

        try:
            run = run_session(self.cfg, self.tuning, record, resume_dir=resume_dir, evaluator=self.evaluator,
                              batch=evaluator, on_iteration=_Progress(self, int(self.get_parameter("log_every").value)),
                              record_validation=record_validation if validate and lanes_up else None,
                              announce=log.info, on_warning=log.warning)
            res, out, best = run.result, dict(run.out), run.result.gains
            if res.bounds is not None:
                for check in res.bounds.checks:
                    log.info(f"bounds: {check.line()}")
                for warning in res.bounds.warnings:
                    log.warning(f"warning: {warning}")
            out.update(evaluator=self.evaluator, lanes=[lane.namespace for lane in self.lanes] if lanes_up else [])
            if run.directory:
                out["gains_file"] = str(run.directory / "gains.yaml")
            if not lanes_up:
                if validate:
                    validation = simulate(run.cfg, best).score
                    out["validation"] = validation.as_json()
                    out["validation_bag"] = None
                    log.info(f"validated k = ({best[0]:.2f}, {best[1]:.2f}, {best[2]:.2f}) in-process: "
                             f"J = {validation.J:.6e}")
                out["controller_gains"] = None
                return out
            for lane in self.lanes:
                lane.prepare(run.cfg)
                reason = lane.set_gains(best)
                if reason:
                    raise HasControlError(f"{lane.controller_name} rejected the best gains {best}: {reason}")
            if validate:
                bag = run.bag
                if bag is None:
                    bag = scratch / "validation"
                    self.lanes[0].run(best, run.cfg, bag, timeout)
                validation, _ = score_bag(bag, on_warning=log.warning)
                out["validation"] = validation.as_json()
                out["validation_bag"] = str(bag) if run.bag else None
                log.info(f"validated k = ({best[0]:.2f}, {best[1]:.2f}, {best[2]:.2f}) through the graph: "
                         f"J = {validation.J:.6e} (batch J = {res.result.fun:.6e})")
            out["controller_gains"] = self.lanes[0].gains()
            return out
        finally:
            if evaluator is not None:
                evaluator.close()
            shutil.rmtree(scratch, ignore_errors=True)

    def _announce_graph(self, cfg, keep: bool, episodes: Path) -> None:
        """Before a graph tuning: how many episodes, how long (from a lock-step rate
        of 1 000–20 000 samples/s per lane), and what the bags take."""
        t = self.tuning.swarm
        count = t.particles * t.iterations
        samples = cfg.episode.samples
        lanes = len(self.lanes)
        per_bag = samples * BAG_BYTES_PER_SAMPLE
        fast, slow = (count * samples / lanes / rate for rate in (20_000.0, 1_000.0))
        self.get_logger().info(
            f"graph tuning: {count} episodes of {samples} samples over {lanes} lane(s), about "
            f"{_duration(fast)} to {_duration(slow)}; each episode's bag ~{per_bag / 1e6:.1f} MB, "
            + (f"kept under {episodes} ({count * per_bag / 1e9:.2f} GB in all)" if keep
               else "scored then deleted (keep_episodes:=true keeps them)") + "; ~/progress shows the ETA")


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def main(args=None):
    failed = []

    def serve(executor, node: TunerNode) -> None:
        if node.get_parameter("autostart").value:
            node.start()
            node.get_logger().info("ready: tuning (~/cancel stops it, ~/status tells)")
            spin(executor, done=node.done.is_set)
            failed.append(bool(node.error))
        else:
            node.get_logger().info("ready: call ~/start to tune (~/cancel, ~/status)")
            spin(executor)
    node_main(args, TunerNode, serve)
    if any(failed):
        raise SystemExit(2)
