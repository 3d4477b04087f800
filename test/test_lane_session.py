"""One tuning session over the tuner node's lanes (has_control.tuning.lane_session), with
stand-in lanes: no ROS. The node graph itself is test_tuner.py's."""
import pytest

from has_control.common.errors import HasControlError
from has_control.config import with_horizon
from has_control.core.episode import simulate
from has_control.core.params import Config
from has_control.tuning.lane_session import LaneSession
from has_control.tuning.service_settings import Settings
from has_control.tuning.tuner import load_tuning, tune

CFG = with_horizon(Config(), 1.5)
TUNING = load_tuning().replace(variant="pso-cp-tvac", iterations=2, particles=3)


class Log:
    def __init__(self):
        self.lines = []

    def info(self, line):
        self.lines.append(("info", line))

    def warning(self, line):
        self.lines.append(("warning", line))

    def error(self, line):
        self.lines.append(("error", line))


class Lane:
    """A plant/controller pair that is there at once and scores an episode as the library does."""

    def __init__(self, namespace, ready=True, refuse=None):
        self.namespace, self.controller_name = namespace, f"{namespace}/controller"
        self._ready, self.refuse = ready, refuse
        self.gains_set, self.episodes, self.prepared = [], [], []

    def ready(self):
        return self._ready

    def bring_up(self):
        pass

    def prepare(self, cfg):
        self.prepared.append(cfg.episode.samples)

    def set_gains(self, gains):
        self.gains_set.append(tuple(gains))
        return self.refuse

    def gains(self):
        return list(self.gains_set[-1])

    def parameters(self):
        return {"controller": {}, "plant": {}}

    def run(self, gains, cfg, bag, timeout):
        self.episodes.append(tuple(gains))
        s = simulate(cfg, gains).score
        return (s.J, s.e_max, s.e_mu, s.e_sigma)


def settings(evaluator="batch", validate=True, lane_timeout=0.05):
    return Settings(CFG, TUNING, evaluator, None, None, False, 10.0, validate, 1e-6, False, 1, lane_timeout)


def session(s, lanes, statuses=None, rows=None, log=None):
    return LaneSession(s, lanes, log or Log(), (rows if rows is not None else []).append, lambda: None,
                       (statuses if statuses is not None else []).append)


@pytest.fixture(scope="module")
def library():
    return tune(CFG, TUNING)


def test_without_lanes_the_batch_session_validates_in_process(library):
    statuses, rows, log = [], [], Log()
    out = session(settings(), [Lane("/", ready=False)], statuses, rows, log).run()
    assert out["gains"] == list(library.gains) and out["validation"]["J"] == library.result.fun
    assert out["lanes"] == [] and out["controller_gains"] is None and out["evaluator"] == "batch"
    assert len(rows) == TUNING.swarm.iterations and statuses[-1].endswith("in-process")
    assert any(s == "info" and line.startswith("no plant/controller lanes found") for s, line in log.lines)


def test_found_lanes_get_the_best_gains(library):
    lanes = [Lane("/sim0"), Lane("/sim1")]
    out = session(settings(validate=False), lanes).run()
    assert out["lanes"] == ["/sim0", "/sim1"] and out["controller_gains"] == list(library.gains)
    assert all(lane.gains_set == [tuple(library.gains)] and lane.prepared == [CFG.episode.samples]
               for lane in lanes)
    assert "validation" not in out and all(lane.episodes == [] for lane in lanes)


def test_a_lane_that_refuses_the_best_gains_fails_the_session_naming_it():
    with pytest.raises(HasControlError, match="/sim1/controller rejected the best gains"):
        session(settings(validate=False), [Lane("/sim0"), Lane("/sim1", refuse="k1 out of range")]).run()


def test_the_graph_evaluator_runs_every_candidate_on_the_lanes(library):
    lanes = [Lane("/sim0"), Lane("/sim1")]
    log = Log()
    out = session(settings("graph", validate=False), lanes, log=log).run()
    assert sum(len(lane.episodes) for lane in lanes) == TUNING.swarm.particles * TUNING.swarm.iterations
    assert out["gains"] == list(library.gains) and out["evaluator"] == "graph"     # the library's scores
    assert any(line.startswith("graph tuning: 6 episodes") for _, line in log.lines)


def test_graph_lanes_missing_are_one_error_naming_them():
    with pytest.raises(HasControlError, match=r"lanes \['/sim0'\]: .* not found within 0.05 s"):
        session(settings("graph"), [Lane("/sim0", ready=False)]).run()
