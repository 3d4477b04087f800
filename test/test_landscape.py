"""has-control landscape: J over 2-D slices through a point, minima and bound found from the grid."""
import json
import time

import numpy as np
import pytest
from conftest import one_line

from has_control.cli.main import main
from has_control.tuning.landscape import MAX_EPISODES, check_plan, planned_episodes, slices

LOWER, UPPER = [150.0, 150.0, 150.0], [1200.0, 800.0, 800.0]


def test_a_bowl_has_one_minimum_per_slice_and_one_batch_call():
    calls = []

    def bowl(k, centre=np.array([500.0, 300.0, 400.0])):
        calls.append(len(k))
        return np.sum(((np.asarray(k) - centre) / 100.0) ** 2, axis=1)
    grid = slices(bowl, (500.0, 300.0, 400.0), LOWER, UPPER, points=21, beyond=0.0)
    assert calls == [3 * 21 * 21]
    for s in grid:
        (m,) = s.minima()
        i, j = s.axes
        centre = (500.0, 300.0, 400.0)
        assert abs(m[0] - centre[i]) <= (UPPER[i] - LOWER[i]) / 20
        assert abs(m[1] - centre[j]) <= (UPPER[j] - LOWER[j]) / 20
        assert s.best() == s.best_inside() == m


def test_a_cost_falling_past_the_bound_has_its_lowest_J_outside_the_box():
    def falling(k):                                   # lower J for higher k1, whatever k2, k3
        return 1.0 / np.asarray(k)[:, 0] + 1e-9 * np.asarray(k)[:, 1]
    (s,) = slices(falling, (600.0, 300.0, 300.0), LOWER, UPPER, points=11, beyond=0.5, pairs=[(0, 1)])
    assert 1200.0 in s.xi and s.xi[-1] >= 1200.0 + 0.4 * 1050.0 and s.best()[0] == s.xi[-1]
    assert s.best_inside()[0] == 1200.0 and s.best()[2] < s.best_inside()[2]


def test_the_cli_draws_and_prints_the_slices(tmp_path, capsys):
    png = tmp_path / "l.png"
    assert main(["landscape", "--points", "5", "--duration", "1.5", "--point", "400", "400", "400",
                 "--plot", str(png), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["gains"] for s in doc["slices"]] == [["k1", "k2"], ["k1", "k3"], ["k2", "k3"]]
    assert all(len(s["J"]) == 5 and len(s["J"][0]) == 5 for s in doc["slices"]) and doc["episodes"] == 75
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert main(["landscape", "--point", "400", "400", "-1"]) == 2
    assert "--point: K3 = '-1'" in capsys.readouterr().err


def test_the_landscape_bounds_slices_times_points_squared_times_scenarios_before_allocation(tmp_path, capsys):
    many = tmp_path / "many.yaml"
    many.write_text("random: {count: 1000, seed: 1, ranges: {plant.mass: [1200.0, 1800.0]}}\n")
    t0 = time.perf_counter()
    one_line(capsys, ["landscape", "--points", "300", "--scenarios", str(many)], "--points 300",
             "1,000 scenarios", "270,000,000 episodes", f"limit of {MAX_EPISODES:,}")
    assert time.perf_counter() - t0 < 30
    assert planned_episodes(300) == MAX_EPISODES and check_plan(300) == MAX_EPISODES      # nominal: as before
    assert check_plan(9, 1000) == 243_000

    def never(k):
        raise AssertionError("the objective was called")
    with pytest.raises(Exception, match="episodes, above the limit"):
        slices(never, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), (2.0, 2.0, 2.0), points=20, scenarios=1000)
