"""The run measures a machine's requirements are stated in
(has_control.core.measures): one arithmetic for the batch kernel and a
series, the paper's J untouched, and the high-pass measure's theory."""
import math

import numpy as np
import pytest

from has_control.config import build_config, load_config
from has_control.core.episode import evaluate_configs, evaluate_measured, series_measures, simulate
from has_control.core.measures import MEASURES, measure_parameters, score_measures

GAINS = np.array([[150.0, 158.0, 162.0], [300.0, 300.0, 300.0], [170.0, 170.0, 175.0]])


@pytest.fixture(scope="module", params=["reference", "spool"])
def cfg(request):
    if request.param == "reference":
        return load_config()
    return build_config({"plant.valve_frequency": 100.0, "plant.valve_limit": 5e-3, "plant.delay": 1,
                         "simulation.horizon": 3.0}, source="test")


def test_the_batch_measures_are_the_series_measures_and_j_is_the_evaluators(cfg):
    runs = evaluate_measured(GAINS, [cfg])
    np.testing.assert_array_equal(runs[:, :, :4], evaluate_configs(GAINS, [cfg]))
    for p, g in enumerate(GAINS):
        m = series_measures(simulate(cfg, tuple(g)), cfg)
        assert list(m.values()) == list(runs[p, 0, 4:])          # bit for bit


def test_the_windowed_cost_is_the_costs_tail_and_the_pressures_bound_the_run(cfg):
    runs = evaluate_measured(GAINS, [cfg])
    col = dict(zip(("J", "e_max", "e_mu", "e_sigma") + MEASURES, np.moveaxis(runs[:, 0], -1, 0)))
    assert np.all(col["J_window"] < col["J"]) and np.all(col["J_window"] > 0.0)
    tr = simulate(cfg, tuple(GAINS[0]))
    assert col["p_min"][0] == min(tr["P1"].min(), tr["P2"].min())
    assert col["p_max"][0] == max(tr["P1"].max(), tr["P2"].max())
    assert col["u_peak"][0] == np.abs(tr["u"]).max()
    if cfg.plant.valve_limit == 0.0:
        assert np.all(col["at_stop"] == 0.0)                    # no travel, no stop


@pytest.mark.parametrize("f", [2.0, 200.0])
def test_hf_rms_of_a_sine_follows_the_first_order_high_pass(f):
    """A command A·sin(2πft) through u − lowpass(u) at 20 Hz: RMS A/√2·|H|, |H| = r/√(1 + r²), r = f/20."""
    cfg = load_config()
    ep = cfg.episode.as_array()
    n = cfg.episode.samples
    t = np.arange(n) * cfg.episode.step
    a = 1e-3
    u = a * np.sin(2 * np.pi * f * t)
    zeros = np.zeros(n)
    out = np.empty(len(MEASURES))
    score_measures(u, zeros, zeros + 1e6, zeros + 1e6, measure_parameters(0.0, 20.0, cfg.episode.step), ep, out)
    r = f / 20.0
    expected = a / math.sqrt(2.0) * r / math.sqrt(1.0 + r * r)
    assert out[MEASURES.index("hf_rms")] == pytest.approx(expected, rel=0.03)
    assert out[MEASURES.index("at_stop")] == 0.0 and out[MEASURES.index("u_peak")] == pytest.approx(a, rel=1e-2)
