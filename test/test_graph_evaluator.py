"""The lanes as a batch evaluator (has_control.tuning.graph_evaluator), with stand-in lanes: no ROS."""
import threading
import time

import numpy as np
import pytest

from has_control.common.errors import HasControlError
from has_control.tuning.graph_evaluator import UNSCORED, GraphEvaluator


class _Lane:
    """Writes the bag it is given and scores a candidate by its gains: J = k1 + k2 + k3."""

    def __init__(self, name, busy):
        self.name, self.busy, self.runs = name, busy, []

    def run(self, gains, cfg, bag, timeout):
        with self.busy["lock"]:
            self.busy["now"] += 1
            self.busy["most"] = max(self.busy["most"], self.busy["now"])
        bag.mkdir(parents=True)
        time.sleep(0.02)
        self.runs.append((tuple(gains), cfg, bag.name, timeout))
        with self.busy["lock"]:
            self.busy["now"] -= 1
        return UNSCORED if gains[0] < 0 else (float(sum(gains)), 1.0, 2.0, 3.0)


def _lanes(n):
    busy = {"lock": threading.Lock(), "now": 0, "most": 0}
    return [_Lane(f"/sim{i}", busy) for i in range(n)], busy


def test_every_candidate_runs_on_a_free_lane_and_comes_back_in_order(tmp_path):
    lanes, busy = _lanes(2)
    announced = []
    gains = np.array([[1.0, 2.0, 3.0], [-1.0, 0.0, 0.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
    with GraphEvaluator(lanes, tmp_path, 5.0, announce=announced.append) as ev:
        first = ev(gains, ["cfg"])
        second = ev(gains[:1], ["cfg"])
    assert first.shape == (4, 1, 4) and second.shape == (1, 1, 4)
    assert first[:, 0, 0].tolist() == [6.0, np.inf, 15.0, 24.0]         # each row is its own candidate's
    assert np.isinf(first[1, 0]).all()                                   # unscored: +inf in every column
    assert announced == ["cfg"]                                          # once, before the first episode
    assert busy["most"] == 2                                             # both lanes at once, never more
    names = sorted(r[2] for lane in lanes for r in lane.runs)
    assert names == ["batch0000_candidate000", "batch0000_candidate001", "batch0000_candidate002",
                     "batch0000_candidate003", "batch0001_candidate000"]
    assert all(r[3] == 5.0 for lane in lanes for r in lane.runs)
    assert list(tmp_path.iterdir()) == []                                # scored, then deleted


def test_kept_episodes_stay_and_scenarios_are_refused(tmp_path):
    lanes, _ = _lanes(1)
    with GraphEvaluator(lanes, tmp_path, 1.0, keep=True) as ev:
        ev([[1.0, 1.0, 1.0]], ["cfg"])
        with pytest.raises(HasControlError, match="one configuration, not 2"):
            ev([[1.0, 1.0, 1.0]], ["a", "b"])
    assert [p.name for p in tmp_path.iterdir()] == ["batch0000_candidate000"]


def test_the_check_stops_the_batch_before_an_episode(tmp_path):
    lanes, _ = _lanes(1)

    def check():
        raise KeyboardInterrupt("cancelled")
    with GraphEvaluator(lanes, tmp_path, 1.0, check=check) as ev:
        with pytest.raises(KeyboardInterrupt):
            ev([[1.0, 1.0, 1.0]], ["cfg"])
    assert lanes[0].runs == []
