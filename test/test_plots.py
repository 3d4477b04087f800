"""Figures, checked through the data they plot (matplotlib Axes), never pixels:
the run figure of a bag or a trace, ``has-control plot``, and the robustness figure."""
import re
import shutil
import subprocess
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from conftest import cli, run_main

from has_control.bag import BagWriter, read_bag, recorded_run, score_bag, write_trace
from has_control.bag.series import run_series
from has_control.cli import main
from has_control.config import build_config, load_scenarios, with_horizon
from has_control.core.episode import simulate
from has_control.core.params import Config
from has_control.core.scenarios import Aggregate, ScenarioScores
from has_control.loop.schedule import LoopStats, _extend
from has_control.loop.plant import missed_message
from has_control.nodes.stack import run_stack
from has_control.plots.figures import draw_convergence_spread, draw_robustness
from has_control.plots.run_figure import draw, view_of_series, view_of_trace
from has_control.tuning.robustness import RobustnessTable, scenario_kind
from has_control.wire import cdr
from has_control.wire.codec import column_label
from has_control.wire.topics import GAINS_COLUMNS

HORIZON = 1.5
UNIT = re.compile(r"\[[^\]]+\]$")


@pytest.fixture(scope="module")
def recorded(recorded):
    """conftest's one recorded run of the session (1.5 s, HORIZON): its bag directory and Config."""
    d, cfg, _ = recorded
    return d, cfg


def _rewrite(src, dst, keep=lambda topic, i: True, custom=True, extra=()):
    """A copy of bag ``src`` at ``dst`` with only the messages ``keep(topic, index)``
    accepts, without the stored parameters unless ``custom``, plus ``extra``
    Float64MultiArray messages (topic, log time [ns], bytes)."""
    bag = read_bag(src)
    with BagWriter(dst, bag.custom_data if custom else {}) as w:
        for topic, ty in bag.types.items():
            if any(keep(topic, i) for i in range(len(bag.messages[topic]))):
                w.add_topic(topic, ty)
        for topic, msgs in bag.messages.items():
            for i, (t, data) in enumerate(msgs):
                if keep(topic, i):
                    w.write(topic, t, data)
        for topic, t, data in extra:
            w.add_topic(topic, "std_msgs/msg/Float64MultiArray")      # no-op for a topic the bag has
            w.write(topic, t, data)
    return dst


def _line(ax, prefix):
    """The one line of ``ax`` labelled ``prefix`` (exactly, else starting with it)."""
    hits = [ln for ln in ax.get_lines() if ln.get_label() == prefix] or [
        ln for ln in ax.get_lines() if str(ln.get_label()).startswith(prefix)]
    assert len(hits) == 1, [ln.get_label() for ln in ax.get_lines()]
    return hits[0]


@pytest.mark.ros
def test_the_plotted_error_is_the_scored_error_over_the_shaded_metric_window(recorded):
    d, cfg = recorded
    score, _ = score_bag(d)
    e1 = recorded_run(read_bag(d))["e1"]
    rf = draw([view_of_series(run_series(d))])
    ax = rf.axes["error"]
    line = _line(ax, "|e1|")
    np.testing.assert_allclose(line.get_ydata() / 1e6, np.abs(e1), rtol=1e-12, atol=0)
    np.testing.assert_array_equal(line.get_xdata(), np.arange(len(e1)) * cfg.episode.step)
    assert ax.get_yscale() == "log" and ax.get_ylabel() == "|e1| [µm]"
    lo, hi = cfg.episode.window()
    span = ax.patches[0]                                      # axvspan: a rectangle, x in data
    dt = cfg.episode.step
    assert (span.get_x(), span.get_x() + span.get_width()) == pytest.approx((lo * dt, hi * dt), abs=1e-12)
    texts = " ".join(t.get_text() for t in ax.texts)
    assert f"e_max {score.e_max * 1e6:.3g}" in texts and f"e_σ {score.e_sigma * 1e6:.3g}" in texts
    assert rf.views[0].metrics == (score.e_max, score.e_mu, score.e_sigma)   # score's arithmetic, bit for bit
    matplotlib.pyplot.close(rf.fig)


@pytest.mark.ros
def test_every_panel_names_its_unit_and_plots_the_run_in_them(recorded):
    d, _ = recorded
    run = recorded_run(read_bag(d))
    rf = draw([view_of_series(run_series(d))])
    for name, ax in rf.axes.items():
        assert UNIT.search(ax.get_ylabel()), (name, ax.get_ylabel())
    assert rf.axes["gains"].get_xlabel() == "time t [s]"
    np.testing.assert_allclose(_line(rf.axes["position"], "y,").get_ydata(), run.y * 1e3, rtol=1e-15)
    np.testing.assert_allclose(rf.axes["valve"].get_lines()[0].get_ydata(), run.u * 1e3, rtol=1e-15)
    np.testing.assert_allclose(_line(rf.axes["pressure"], "P1").get_ydata(), run.p1 * 1e-5, rtol=1e-15)
    np.testing.assert_allclose(_line(rf.axes["pressure"], "P2").get_ydata(), run.p2 * 1e-5, rtol=1e-15)
    matplotlib.pyplot.close(rf.fig)


def test_valve_limit_and_projection_bounds_are_drawn_from_the_runs_config():
    cfg = build_config({"plant.valve_limit": 5e-3}, base=with_horizon(Config(), HORIZON))
    tr = simulate(cfg)
    rf = draw([view_of_trace(tr, cfg)])
    flat = [ln for ln in rf.axes["valve"].get_lines() if len(set(ln.get_ydata())) == 1]
    assert sorted(ln.get_ydata()[0] for ln in flat) == pytest.approx([-5.0, 5.0])
    for key, col, k, scale in (("a1", "a1_hat", 0, 1.0), ("a2", "a2_hat", 1, 1e12)):
        ax = rf.axes[key]
        np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), tr[col] * scale, rtol=1e-15)
        bounds = sorted(ln.get_ydata()[0] for ln in ax.get_lines()[1:])
        assert bounds == pytest.approx([cfg.adaptation.lower[k] * scale, cfg.adaptation.upper[k] * scale])
    matplotlib.pyplot.close(rf.fig)
    rf = draw([view_of_trace(simulate(with_horizon(Config(), HORIZON)), Config())])
    assert not [ln for ln in rf.axes["valve"].get_lines() if len(set(ln.get_ydata())) == 1]  # no limit: none
    matplotlib.pyplot.close(rf.fig)


@pytest.mark.ros
def test_the_gains_in_force_step_where_a_tuner_changed_them(recorded, tmp_path):
    d, cfg = recorded
    change = cdr.encode_float64_arrays([[0.6, 300.0, 310.0, 320.0]], column_label(GAINS_COLUMNS))[0]
    b = _rewrite(d, tmp_path / "retuned", extra=[("/controller/gains", 600_000_000, change)])
    s = run_series(b)
    np.testing.assert_array_equal(s.gains_t, [0.0, 0.6])
    rf = draw([view_of_series(s)])
    k1 = _line(rf.axes["gains"], "k1")
    assert list(k1.get_xdata()) == pytest.approx([0.0, 0.6, s.t[-1]])
    assert list(k1.get_ydata()) == [150.0, 300.0, 300.0]
    matplotlib.pyplot.close(rf.fig)


@pytest.mark.ros
def test_a_realtime_bag_with_unanswered_samples_is_plotted_with_them_marked(recorded, tmp_path):
    d, cfg = recorded
    dropped = {100, 2001, 2002}
    b = _rewrite(d, tmp_path / "rt", keep=lambda topic, i: not (topic == "/command" and i in dropped))
    with pytest.raises(Exception, match="not one message per sample"):
        score_bag(b)                                          # scoring refuses it; a figure shows it
    v = view_of_series(run_series(b))
    np.testing.assert_allclose(v.missed_t, sorted(i * cfg.episode.step for i in dropped))
    assert np.isnan(v.u[list(dropped)]).all() and v.metrics_note == ""   # e1 is whole: the metrics are exact
    rf = draw([v])
    rug = _line(rf.axes["valve"], "no command recorded (3 samples)")
    np.testing.assert_allclose(rug.get_xdata(), v.missed_t)
    matplotlib.pyplot.close(rf.fig)
    out = tmp_path / "rt.png"
    r = cli("plot", b, "--out", out)
    assert r.returncode == 0 and out.read_bytes()[:4] == b"\x89PNG", r.stderr


@pytest.mark.ros
def test_missed_and_fail_safe_samples_recorded_by_a_realtime_stack_are_marked(recorded, tmp_path):
    d, cfg = recorded
    stats = LoopStats(300_000)
    for i in (5, 6, 7, 20):                                   # as run_paced counts them
        _extend(stats.missed_spans, i)
    _extend(stats.failsafe_spans, 7)
    assert stats.missed_spans == [[5, 7], [20, 20]] and stats.failsafe_spans == [[7, 7]]
    log = [(i, 0.0, 0.0, 0.0, 0.0, i * 1e-6) for i in range(30)]  # (sample, y, ẏ, P1, P2, u it ran with)
    failsafe = {i for a, b in stats.failsafe_spans for i in range(a, b + 1)}
    msgs = [missed_message(i, cfg.episode.step, log[i][-1], i in failsafe)      # as the plant reports them
            for a, b in stats.missed_spans for i in range(a, b + 1)]
    rows = cdr.float64_arrays(msgs)
    np.testing.assert_allclose(rows, [[5 * 3e-4, 5e-6, 0], [6 * 3e-4, 6e-6, 0], [7 * 3e-4, 7e-6, 1],
                                      [20 * 3e-4, 2e-5, 0]], rtol=1e-15)
    b = _rewrite(d, tmp_path / "rt", extra=[("/plant/missed", round(r[0] * 1e9), m) for r, m in zip(rows, msgs)])
    s = run_series(b)
    assert list(s.missed) == [5, 6, 7, 20] and list(s.failsafe) == [7]
    rf = draw([view_of_series(s)])
    valve = rf.axes["valve"]
    np.testing.assert_allclose(_line(valve, "missed: ran on the held command (4 samples)").get_xdata(),
                               np.array([5, 6, 7, 20]) * cfg.episode.step)
    np.testing.assert_allclose(_line(valve, "fail-safe: valve centred (1 sample)").get_xdata(), [7 * cfg.episode.step])
    matplotlib.pyplot.close(rf.fig)
    assert run_series(d).missed is None                       # a lock-step bag does not say


@pytest.mark.ros
def test_a_realtime_stack_bag_records_every_missed_sample(tmp_path):
    cfg = with_horizon(Config(), HORIZON)
    run = run_stack(cfg, record=tmp_path / "rt", realtime=True, domain_id=230)
    bag = read_bag(tmp_path / "rt")
    assert "/plant/missed" in bag.types                       # declared even when nothing was missed
    s = run_series(tmp_path / "rt")
    assert len(s.missed) == run.loop["missed_samples"] and len(s.failsafe) == run.loop["failsafe_samples"]
    assert list(s.missed[:len(run.missed_at)]) == run.missed_at


@pytest.mark.ros
def test_a_bag_converted_by_rosbags_convert_plots_like_the_original(recorded, tmp_path):
    d, cfg = recorded
    exe = shutil.which("rosbags-convert", path=str(Path(sys.executable).parent))
    assert exe, "rosbags-convert (from requirements.txt's rosbags) is not installed beside python"
    conv = tmp_path / "converted"
    r = subprocess.run([exe, "--src", str(d), "--dst", str(conv), "--dst-storage", "mcap"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    warnings = []
    a, b = run_series(d), run_series(conv, on_warning=warnings.append)
    assert not b.parameters and "no has_control/parameters" in warnings[0]   # rosbags-convert drops custom_data
    np.testing.assert_array_equal(a.e1, b.e1)
    assert b.cfg.episode.step == pytest.approx(cfg.episode.step, rel=1e-12)
    assert view_of_series(b).window == pytest.approx(view_of_series(a).window)
    r = cli("plot", conv, "--out", tmp_path / "c.pdf")
    assert r.returncode == 0 and (tmp_path / "c.pdf").read_bytes()[:4] == b"%PDF", r.stderr


@pytest.mark.ros
def test_a_bag_from_another_recorder_plots_on_its_own_grid(recorded, tmp_path):
    """Wall-clock stamps with jitter, no parameters (a real machine's bag): the
    grid starts at the first state, Δt is the stamps' median step."""
    d, cfg = recorded
    run = recorded_run(read_bag(d))
    n, t0 = len(run.t), 1_764_600_000_123_456_789
    stamps = t0 + np.arange(n) * 300_000 + np.random.default_rng(1).integers(-40_000, 40_000, n)
    zeros = np.zeros(n)
    with BagWriter(tmp_path / "machine") as w:
        for topic, ty, msgs in (
                ("/hw/state", "sensor_msgs/msg/JointState", cdr.encode_joint_states(
                    stamps, ["chamber_2", "actuator", "chamber_1"], np.column_stack([zeros, run.y, zeros]),
                    np.column_stack([zeros, run.ydot, zeros]), np.column_stack([run.p2, zeros, run.p1]))),
                ("/hw/command", "sensor_msgs/msg/JointState", cdr.encode_joint_states(
                    stamps, ["valve"], run.u[:, None])),
                ("/hw/controller/reference", "std_msgs/msg/Float64MultiArray", cdr.encode_float64_arrays(
                    np.column_stack([stamps / 1e9, run.x1d, zeros, zeros, zeros])))):
            w.add_topic(topic, ty)
            for t, m in zip(stamps, msgs):
                w.write(topic, int(t), m)
    s = run_series(tmp_path / "machine", on_warning=lambda m: None)
    assert s.cfg.episode.step == pytest.approx(3e-4, rel=1e-3) and len(s.t) == n
    np.testing.assert_array_equal(s.y, run.y)                 # joints found by name, not by position
    np.testing.assert_array_equal(s.p1, run.p1)
    np.testing.assert_allclose(s.e1, run["e1"], rtol=0, atol=1e-15)
    r = cli("plot", tmp_path / "machine", "--out", tmp_path / "m.png")
    assert r.returncode == 0, r.stderr


@pytest.mark.system
def test_a_tuner_sessions_validation_bag_and_the_tune_figures(tmp_path):
    out = tmp_path / "tuned"
    r = cli("tune", "--variant", "pso-cp-tvac",
            "--particles", "4", "--iterations", "2", "--duration", HORIZON, "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    for fig in ("convergence.png", "gains.png", "tracking.png"):
        assert (out / fig).read_bytes()[:4] == b"\x89PNG"
    s = run_series(out / "session")                           # the /validation run among the tuner's topics
    import json
    gains = json.loads(r.stdout)["gains"]
    ref = simulate(with_horizon(Config(), HORIZON), gains)
    np.testing.assert_array_equal(s.e1, ref["e1"])
    np.testing.assert_array_equal(s.gains[-1], gains)
    r = cli("plot", out / "session", "--window", "0.2", "0.8", "--out", tmp_path / "w.svg")
    assert r.returncode == 0 and b"<svg" in (tmp_path / "w.svg").read_bytes()[:500], r.stderr


@pytest.mark.ros
def test_cli_overlays_several_bags_named_by_their_gains(recorded, tmp_path):
    d, cfg = recorded
    other = tmp_path / "other"
    with BagWriter(other, {"has_control/parameters": read_bag(d).custom_data["has_control/parameters"]}) as w:
        write_trace(w, simulate(cfg, (300.0, 310.0, 320.0)), cfg)
    out = tmp_path / "both.png"
    r = cli("plot", d, other, "--out", out)
    assert r.returncode == 0 and r.stdout.strip() == f"wrote {out}" and out.stat().st_size < 300_000, r.stderr
    from has_control.cli.plot import _names
    from has_control.plots.run_figure import gains_text
    assert _names([str(d), str(other)], [run_series(d), run_series(other)], gains_text) == [
        "k = (150, 158, 162)", "k = (300, 310, 320)"]


@pytest.mark.parametrize("case, culprit", [
    ("not-a-bag", "not an MCAP file"),
    ("no-state", "no '…/state'"),
    ("suffix", "cannot be written as 'xyz'"),
    ("reversed-window", "--window 1 0.5: empty"),
    ("window-outside", "--window 5 6:"),
])
@pytest.mark.ros
def test_bad_input_is_one_line_and_exit_2_and_no_figure(recorded, tmp_path, case, culprit, capsys):
    d, _ = recorded
    out = tmp_path / "f.png"
    args = {"not-a-bag": [tmp_path / "x.mcap"], "no-state": [tmp_path / "nostate"],
            "suffix": [d, "--out", tmp_path / "f.xyz"], "reversed-window": [d, "--window", "1", "0.5"],
            "window-outside": [d, "--window", "5", "6"]}[case]
    (tmp_path / "x.mcap").write_text("hello")
    _rewrite(d, tmp_path / "nostate", keep=lambda topic, i: topic != "/state")
    r = run_main(capsys, "plot", *args, *([] if "--out" in args else ["--out", out]))
    assert r.returncode == 2 and culprit in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not out.exists() and not (tmp_path / "f.xyz").exists()


def _table(kinds_of):
    """Four gain sets on five scenarios, J chosen: a robust one 1 % better on two of them."""
    names = ("drift-a", "nominal", "road-x", "noisy", "drift-b")
    j = np.array([[1.0, 2.0, 4.0, 1.0, 3.0],           # baseline
                  [0.99, 2.02, 3.96, 1.01, 3.03],      # close to it
                  [1e3, 2e4, np.inf, 5e2, 1e5],        # far, and diverged once
                  [5.0, 1.0, 8.0, 2.0, 6.0]])
    metrics = np.stack([j, j, j, j], axis=-1)
    return RobustnessTable(("nominal-tuned", "robust-tuned", "paper", "manual"), ((1, 1, 1),) * 4,
                           ScenarioScores(names, metrics, Aggregate("mean")), tuple(kinds_of[n] for n in names)), j


def test_robustness_figure_plots_j_relative_to_the_baseline_grouped_by_kind():
    kinds = {"drift-a": "drift", "nominal": "nominal", "road-x": "road", "noisy": "noise", "drift-b": "drift"}
    table, j = _table(kinds)
    fig, ax, pct, order = draw_robustness(table)
    assert [table.scores.names[s] for s in order] == ["nominal", "road-x", "drift-a", "drift-b", "noisy"]
    assert [t.get_text() for t in pct.get_xticklabels()] == ["nominal", "road-x", "drift-a", "drift-b", "noisy"]
    assert ax.get_yscale() == "log" and UNIT.search(ax.get_ylabel()) and UNIT.search(pct.get_ylabel())
    close = _line(ax, "robust-tuned")
    np.testing.assert_allclose(close.get_ydata(), j[1, order] / j[0, order], rtol=1e-15)
    far = _line(ax, "paper")                                  # the diverged scenario is not a ratio...
    assert len(far.get_ydata()) == 4 and len(_line(ax, "paper: diverged (1)").get_ydata()) == 1  # ...but an x
    heights = [p.get_height() for p in pct.patches]
    np.testing.assert_allclose(heights, (j[1, order] / j[0, order] - 1) * 100, rtol=1e-12)
    assert "lower J on 2 of 5 scenarios" in pct.get_legend().get_texts()[0].get_text()
    assert [t.get_text() for t in ax.texts] == ["nominal (1)", "road (1)", "drift (2)", "noise (1)"]
    matplotlib.pyplot.close(fig)
    fig, ax, pct, _ = draw_robustness(table, baseline="manual")  # none close to manual: no % panel
    assert pct is None and ax.get_ylabel() == "J / J(manual) [1]"
    matplotlib.pyplot.close(fig)


def test_scenario_kinds_of_the_shipped_sets():
    kinds = [scenario_kind(s) for s in load_scenarios("config/scenarios.yaml")]
    assert kinds[:2] == ["nominal", "road"] and set(kinds[2:]) == {"drift"}
    held = [scenario_kind(s) for s in load_scenarios("config/scenarios_heldout.yaml")]
    assert held[:2] == ["road", "road"] and set(held[2:]) == {"drift"}


class _Hist:
    def __init__(self, c):
        self.best_cost = c


class _Result:
    def __init__(self, costs):
        self.history = [_Hist(c) for c in costs]


def test_convergence_legend_says_how_many_seeds_it_averages():
    fig = draw_convergence_spread([("pso", [_Result([3.0, 2.0, 1.0])]),
                                   ("pso-cp", [_Result([3.0, 1.0, 1.0]), _Result([5.0, 3.0, 1.0])])])
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "pso", "pso-cp (mean of 2 seeds, band: min-max)"]
    np.testing.assert_array_equal(ax.get_lines()[1].get_ydata(), [4.0, 2.0, 1.0])
    assert ax.get_yscale() == "linear" and UNIT.search(ax.get_ylabel())    # J within a decade
    matplotlib.pyplot.close(fig)
    fig = draw_convergence_spread([("pso", [_Result([300.0, 2.0, 1.0])])])
    assert fig.axes[0].get_yscale() == "log"                                 # over decades
    matplotlib.pyplot.close(fig)


def test_a_label_with_dollar_signs_is_drawn_as_written(tmp_path):
    # a bag named 'a$b_{$x' (or any label with '$') was once parsed as mathtext and raised
    from has_control.plots.identification import plot_validation
    t = np.arange(50) * 3e-4
    states = np.column_stack([np.sin(t), np.cos(t), 5e6 + t, 4e6 + t])
    out = plot_validation(t, states, states * 1.01, {"y": 99.0, "P1": 98.0, "P2": 97.0}, tmp_path / "v.png",
                          "Identified plant against run$_{$x^ (held out)")
    assert out.read_bytes()[:4] == b"\x89PNG"
    cfg = with_horizon(Config(), 1.2)
    fig = draw([view_of_trace(simulate(cfg), cfg, "gains $k_1$ and 50$")], title="$x_{").fig
    assert fig._suptitle.get_text() == "$x_{"
    import matplotlib.pyplot as plt
    fig.canvas.draw()                           # the text is laid out: no mathtext parse
    plt.close(fig)


@pytest.mark.parametrize("command", [["robustness", "--gains", "400", "400", "400"], ["simulate"]])
def test_a_figure_format_matplotlib_cannot_write_is_one_line_before_any_run(tmp_path, capsys, command):
    p = tmp_path / "s.yaml"
    p.write_text("scenarios:\n  nominal: {}\n")
    extra = ["--scenarios", str(p)] if command[0] == "robustness" else []
    with pytest.raises(SystemExit) as status:                   # argparse: before anything runs
        main([*command, *extra, "--duration", "1.2", "--plot", str(tmp_path / "r.txt")])
    assert status.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "r.txt" in err and "png" in err, err
