"""One tuning session over the tuner node's lanes (ROS-free): the graph or the batch evaluator,
the best gains set on every lane, validated through the graph.

:class:`LaneSession` runs :func:`has_control.tuning.session.run_session` (the
same runner as ``has-control tune``) with candidates scored by the batch
evaluator or through the lanes
(:class:`~has_control.tuning.graph_evaluator.GraphEvaluator`), then sets the
best gains on every lane and (``validate_best``) validates them through the
graph against the library's J of the same gains
(:mod:`has_control.tuning.validation`); without lanes (evaluator batch, none
found) it validates in-process.

A lane is any object with the methods of :class:`has_control.nodes.lanes.Lane`
(``ready``, ``bring_up``, ``prepare``, ``set_gains``, ``gains``, ``parameters``,
``run``) and its ``namespace`` and ``controller_name``; the log any object with
``info`` and ``warning`` (an rclpy logger).
"""
from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Callable

from has_control.bag import score_bag
from has_control.common.errors import HasControlError
from has_control.config import config_parameters
from has_control.core.episode import simulate
from has_control.tuning.graph_evaluator import GraphEvaluator
from has_control.tuning.service_progress import Progress, graph_estimate
from has_control.tuning.service_settings import Settings
from has_control.tuning.session import rewrite_result, run_session, write_lanes
from has_control.tuning.validation import lane_differences, validation_block, validation_line

#: With evaluator batch, how long to look for the (optional) lanes once the tuning is done [s].
OPTIONAL_LANES_WAIT = 2.0


class Cancelled(Exception):
    """``~/cancel`` was called: the session stops at the next episode or iteration."""


class LaneSession:
    """One session with ``settings`` over ``lanes`` (see the module). ``publish_progress(row)``
    takes each iteration's progress row, ``check()`` runs before each episode and after
    each iteration (raises :class:`Cancelled` to stop), ``set_status(line)`` hears what it does."""

    def __init__(self, settings: Settings, lanes: list, log, publish_progress: Callable[[list], None],
                 check: Callable[[], None], set_status: Callable[[str], None]):
        self.settings, self.lanes, self.log = settings, lanes, log
        self.publish_progress, self.check, self.set_status = publish_progress, check, set_status
        self._lanes_up: bool | None = None            # are the lanes there (None: not looked for yet)
        self._lane_parameters: list[dict] = []        # the lanes' parameters as read back

    def wait_for_lanes(self, timeout: float | None = None, required: bool = True) -> bool:
        """Wait for every lane's plant and controller (bringing managed ones up);
        False if they are not all there in ``timeout`` [s] and not ``required``."""
        timeout = self.settings.lane_timeout if timeout is None else timeout
        end = time.monotonic() + timeout
        while not all(lane.ready() for lane in self.lanes):
            self.check()
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

    def _optional_lanes(self) -> bool:
        """Are the lanes there? With evaluator batch looked for once (briefly), and said when not."""
        if self._lanes_up is None:
            self._lanes_up = self.wait_for_lanes(min(OPTIONAL_LANES_WAIT, self.settings.lane_timeout),
                                                 required=False)
            if not self._lanes_up:
                self.log.info("no plant/controller lanes found: the batch evaluator alone, validation in-process; "
                              "the best gains are set on no controller")
        return self._lanes_up

    def _read_lane_parameters(self) -> list[dict]:
        """Each lane's controller and plant parameters as they are (read back through their services)."""
        self._lane_parameters = [{"lane": lane.namespace, **lane.parameters()} for lane in self.lanes]
        return self._lane_parameters

    def _record_validation(self, gains, writer, cfg) -> bool:
        """The session's validation through the graph, into the session bag (False: no lanes,
        the session records the in-process run)."""
        if not self._optional_lanes():
            return False
        write_lanes(writer, self._read_lane_parameters())
        self.set_status(f"validating: k = {_k(gains)} through the graph (lane {self.lanes[0].namespace})")
        self.lanes[0].run(gains, cfg, writer.path, self.settings.episode_timeout, writer=writer, prefix="/validation")
        return True

    # --- the session -------------------------------------------------------------
    def run(self) -> dict:
        """The session (see the module); its result (``tune --json``'s keys, the
        evaluator, the lanes, the validation, the controller's gains)."""
        s, log = self.settings, self.log
        scratch = Path(tempfile.mkdtemp(prefix="has_control_tuner_"))
        graph = s.evaluator == "graph"
        evaluator = None
        try:
            if graph:
                self._lanes_up = self.wait_for_lanes(s.lane_timeout)     # batch: looked for once tuned
                directory = s.resume or s.record
                keep = bool(directory) and s.keep_episodes
                episodes = Path(directory) / "episodes" if keep else scratch
                count = s.tuning.swarm.particles * s.tuning.swarm.iterations
                evaluator = GraphEvaluator(self.lanes, episodes, s.episode_timeout, keep, check=self.check,
                                           announce=lambda cfg: log.info(graph_estimate(
                                               count, cfg.episode.samples, len(self.lanes), keep, episodes)))
            progress = Progress(s.log_every, self.set_status, self.publish_progress, log.info, self.check)
            run = run_session(s.cfg, s.tuning, s.record, resume_dir=s.resume, replace=s.force,
                              evaluator=s.evaluator, batch=evaluator, on_iteration=progress,
                              record_validation=self._record_validation if s.validate else None,
                              announce=log.info, on_warning=log.warning)
            return self._finish(run, self._after(run, scratch))
        finally:
            if evaluator is not None:
                evaluator.close()
            shutil.rmtree(scratch, ignore_errors=True)

    def _after(self, run, scratch: Path) -> dict:
        """After the tuning: the bounds logged, the best gains set on every lane and validated
        (through the graph, or in-process without lanes); the result's keys."""
        s, log = self.settings, self.log
        res, out, best = run.result, dict(run.out), run.result.gains
        if res.bounds is not None:
            for check in res.bounds.checks:
                log.info(f"bounds: {check.line()}")
            for warning in res.bounds.warnings:
                log.warning(f"warning: {warning}")
        up = self._optional_lanes()
        out.update(evaluator=s.evaluator, lanes=[lane.namespace for lane in self.lanes] if up else [])
        if run.directory:
            out["gains_file"] = str(run.directory / "gains.yaml")
        if not up:
            if s.validate:
                self.set_status(f"validating: k = {_k(best)} in-process")
                validation = simulate(run.cfg, best).score
                out["validation"] = validation.as_json()
                out["validation_bag"] = None
                log.info(f"validated k = {_k(best)} in-process: J = {validation.J:.6e}")
            out["controller_gains"] = None
            return out
        for lane in self.lanes:
            lane.prepare(run.cfg)
            reason = lane.set_gains(best)
            if reason:
                raise HasControlError(f"{lane.controller_name} rejected the best gains {best}: {reason}")
        if s.validate:
            bag = run.bag
            if bag is None:
                self._read_lane_parameters()
                self.set_status(f"validating: k = {_k(best)} through the graph (lane {self.lanes[0].namespace})")
                bag = scratch / "validation"
                self.lanes[0].run(best, run.cfg, bag, s.episode_timeout)
            validation, _ = score_bag(bag, on_warning=log.warning)
            out["validation"] = self._compare(validation, run.cfg, best, self._lane_parameters, s.tolerance)
            out["validation_bag"] = str(bag) if run.bag else None
        out["controller_gains"] = self.lanes[0].gains()
        return out

    def _finish(self, run, out: dict) -> dict:
        """The result, with its validation, also in ``tune.json`` when the session is recorded."""
        if run.directory is not None:
            rewrite_result(run.directory, out)
        return out

    def _compare(self, validation, cfg, best, lanes: list[dict], tolerance: float) -> dict:
        """The graph's validation against the library's J of the same gains on the tuner's
        model (:mod:`has_control.tuning.validation`), logged (a warning beyond ``tolerance``)."""
        block = validation_block(validation.as_json(), validation.J, simulate(cfg, best).score.J,
                                 lane_differences(config_parameters(cfg), lanes), tolerance)
        if block["agrees"]:                      # (rclpy: one severity per call site)
            self.log.info(validation_line(block, best))
        else:
            self.log.warning(validation_line(block, best))
        return block


def _k(gains) -> str:
    return f"({gains[0]:.2f}, {gains[1]:.2f}, {gains[2]:.2f})"
