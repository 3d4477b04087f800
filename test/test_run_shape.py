"""One run shape and one compiled reference series (#28 item 5)."""
from __future__ import annotations

import numpy as np
import pytest

from has_control.config import build_config
from has_control.core.episode import EpisodeArrays
from has_control.core.reference import reference, reference_series


@pytest.mark.parametrize("kind", ["sine", "step", "chirp", "road", "zero"])
def test_reference_series_is_the_per_sample_reference_bit_for_bit(kind):
    """The compiled series gives every sample's (x1d, ẋ1d, ẍ1d, x1d⁽³⁾) with the
    bits of a Python call of :func:`reference` per sample (what the bag writer,
    the bag readers and the stack did before)."""
    cfg = build_config({"reference.kind": kind, "simulation.horizon": 2.0})
    rp = EpisodeArrays.from_config(cfg).reference
    t = np.arange(cfg.episode.samples) * cfg.episode.step
    one_by_one = np.array([reference(rp, ti) for ti in t])
    series = reference_series(rp, t)
    assert series.shape == (len(t), 4)
    assert np.array_equal(series.view(np.int64), one_by_one.view(np.int64))
    if kind != "zero":
        assert np.ptp(series[:, 0]) > 0                  # a reference that moves: the test can fail
    strided = reference_series(rp, np.repeat(t, 2)[::2])   # any layout of t
    assert np.array_equal(strided, series)


def _written(tmp_path, trace, cfg):
    """``trace`` written as the graph's messages into a bag with the run's parameters."""
    from has_control.bag import PARAMETERS_KEY, BagWriter, parameters_json, write_trace
    w = BagWriter(tmp_path / "run", {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, trace, cfg)
    return w.close()


def test_simulate_and_the_bag_readers_give_one_run_shape(tmp_path):
    """A simulated run, its bag read for a score and read for a figure: three
    producers, one :class:`Run` (same columns, same bits where each has them)."""
    from has_control.bag import score_bag
    from has_control.bag.series import run_series
    from has_control.core.episode import simulate
    from has_control.core.params import Config
    from has_control.core.run import Col, Run
    cfg = build_config({"simulation.horizon": 2.0}, base=Config())
    trace = simulate(cfg)
    bag = _written(tmp_path, trace, cfg)
    _, scored = score_bag(bag, on_warning=lambda line: None)
    series = run_series(bag, on_warning=lambda line: None)
    shared = [Col.t, Col.x1d, Col.y, Col.ydot, Col.P1, Col.P2, Col.u, Col.e1]
    for run in (trace, scored, series):
        assert isinstance(run, Run) and run.data.shape == (cfg.episode.samples, len(Col))
        assert np.array_equal(run.data[:, shared], trace.data[:, shared])
        assert np.array_equal(run.e1, run.x1d - run.y) and np.array_equal(run["P1"], run.p1)
    assert np.array_equal(series.data[:, [Col.a1_hat, Col.a2_hat]], trace.data[:, [Col.a1_hat, Col.a2_hat]])
    assert np.isnan(scored.a1_hat).all()          # a score reads no controller internals: said as NaN, not zero


def test_the_run_figure_draws_the_run_it_is_given(tmp_path):
    """The figure's view holds the producer's Run itself; a crop is a Run of the kept rows."""
    from has_control.core.episode import simulate
    from has_control.core.params import Config
    from has_control.plots.run_figure import crop, view_of_trace
    cfg = build_config({"simulation.horizon": 2.0}, base=Config())
    trace = simulate(cfg)
    view = view_of_trace(trace, cfg)
    assert view.run is trace and np.shares_memory(view.y, trace.data)
    cut = crop(view, 0.2, 0.4)
    keep = (trace.t >= 0.2) & (trace.t <= 0.4)
    assert np.array_equal(cut.run.data, trace.data[keep]) and 0 < len(cut.run) < len(trace)
