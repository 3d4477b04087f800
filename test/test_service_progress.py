"""What the tuner node says while it tunes (has_control.tuning.service_progress): no ROS."""
import math
from pathlib import Path

from has_control.tuning.service_progress import BAG_BYTES_PER_SAMPLE, Progress, duration, graph_estimate


class _Method:
    name, best_f, evaluations = "cma-restarts", 2.5e-4, 30

    def __init__(self):
        self.iteration, self.share, self.done, self.best_x = 0, 0.0, False, [300.0, 400.5, 50.25]

    def progress(self):
        return self.share


def test_each_iteration_is_a_status_a_row_a_log_line_every_nth_and_a_check(monkeypatch):
    clock = iter([10.0, 12.0, 14.0, 16.0])
    monkeypatch.setattr("has_control.tuning.service_progress.time.perf_counter", lambda: next(clock))
    said = {"status": [], "row": [], "log": [], "check": 0}

    def check():
        said["check"] += 1
    bar = Progress(2, said["status"].append, said["row"].append, said["log"].append, check)
    m = _Method()
    bar(m)                                                # iteration 0, nothing of the budget used yet
    m.iteration, m.share = 1, 0.25
    bar(m)                                                # 4 s for a quarter: 12 s left
    m.iteration, m.share, m.done = 3, 1.0, True
    bar(m)                                                # the last is logged although not every 2nd
    assert said["status"][0] == "running: cma-restarts iteration 0 (0 %), best J = 2.500000e-04, ETA inf s"
    assert said["status"][1].endswith("iteration 1 (25 %), best J = 2.500000e-04, ETA 12 s")
    assert said["row"][1] == [1.0, 2.5e-4, 300.0, 400.5, 50.25, 30.0, 4.0, 12.0]
    assert math.isinf(said["row"][0][-1]) and said["row"][2][-1] == 0.0
    assert [line.split(" (")[0] for line in said["log"]] == ["cma-restarts iteration 0", "cma-restarts iteration 3"]
    assert "at k = (300.00, 400.50, 50.25), 30 evaluations" in said["log"][0]
    assert said["check"] == 3


def test_the_graph_estimate_scales_with_the_episodes_and_the_lanes():
    one = graph_estimate(100, 3000, 1, False, Path("/x"))
    two = graph_estimate(100, 3000, 2, True, Path("/x/episodes"))
    # 100 episodes × 3000 samples at 20 000 .. 1 000 samples/s: 15 s .. 5 min on one lane, half on two
    assert "100 episodes of 3000 samples over 1 lane(s), about 15 s to 5 min" in one
    assert "about 8 s to 2 min" in two
    assert f"~{3000 * BAG_BYTES_PER_SAMPLE / 1e6:.1f} MB" in one and "scored then deleted" in one
    assert f"kept under /x/episodes ({100 * 3000 * BAG_BYTES_PER_SAMPLE / 1e9:.2f} GB in all)" in two


def test_a_duration_reads_in_s_min_or_h():
    assert [duration(s) for s in (0.4, 119.0, 120.0, 7199.0, 7200.0)] == ["0 s", "119 s", "2 min", "120 min", "2.0 h"]
