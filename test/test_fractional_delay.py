"""A fractional transport delay of the command: ``plant.delay_fraction``
f interpolates the command linearly between samples i − d and i − d − 1, so a
delay of d + f samples is not rounded to whole ones (the vouching variant's
delay is the group delay it stands for). The library's kernels and the plant
node's step agree bit for bit; f = 0 is the whole-sample delay, bit for bit."""
from __future__ import annotations

import numpy as np
import pytest

from has_control.common.errors import ConfigError
from has_control.config import build_config, load_config, with_horizon
from has_control.core.episode import EpisodeArrays, evaluate, simulate
from has_control.core.params import DELAY_MAX
from has_control.tuning.vouch import UNSEEN_FACTOR, UNSEEN_ZETA, unseen_variants
from has_control.wire import steps
from test_plant_models import node_step_states

MANUAL = (150.0, 158.0, 162.0)


def _cfg(flat: dict, horizon: float = 1.5):
    return with_horizon(build_config(flat, base=load_config()), horizon)


def _applied(flat: dict, u: np.ndarray) -> np.ndarray:
    """The command the valve got at each sample: the plant node's step with an ideal valve (its position is the
    command it is given), fed ``u``."""
    cfg = _cfg(flat)
    arr = EpisodeArrays.from_config(cfg)
    x = steps.plant_state(arr.x0)
    state, clock, scr = steps.STATE_LAYOUT.buffer(), steps.CLOCK_LAYOUT.buffer(), steps.scratch()
    out = np.empty(len(u))
    for i, ui in enumerate(u):
        steps.plant_sample(x, ui, arr.plant, cfg.episode.step, cfg.episode.y_limit, i + 1, cfg.episode.step_ns,
                           state, clock, scr)
        out[i] = x[4]
    return out


@pytest.mark.parametrize("d, f", [(0, 0.25), (1, 0.5), (3, 0.9)])
def test_the_valve_gets_the_command_interpolated_between_the_two_samples_around_the_delay(d, f):
    u = np.random.default_rng(3).uniform(-1e-3, 1e-3, 60)
    got = _applied({"plant.delay": d, "plant.delay_fraction": f}, u)
    padded = np.r_[np.zeros(d + 1), u]
    i = np.arange(len(u)) + d + 1
    np.testing.assert_allclose(got, (1.0 - f) * padded[i - d] + f * padded[i - d - 1], rtol=0, atol=1e-18)


@pytest.mark.parametrize("flat", [
    {"plant.delay": 0, "plant.delay_fraction": 0.4},
    {"plant.delay": 2, "plant.delay_fraction": 0.7, "plant.valve_frequency": 120.0, "plant.valve_limit": 5e-3},
    {"plant.delay": 1, "plant.delay_fraction": 0.3, "plant.friction_coulomb": 150.0, "plant.substeps": 2},
])
def test_the_plant_nodes_step_and_both_library_kernels_delay_fractionally_alike(flat):
    """steps.plant_sample fed the trace's commands steps the trace's states bit for bit; the batch kernel
    gives the trace kernel's J."""
    cfg = _cfg(flat)
    tr = simulate(cfg, MANUAL)
    np.testing.assert_array_equal(node_step_states(cfg, tr["u"]), tr.data[:, 2:6])
    assert evaluate(np.array([MANUAL, MANUAL]), cfg)[0] == tr.score.J


def test_a_fraction_tends_to_the_whole_delays_on_either_side():
    base = {"plant.valve_frequency": 100.0, "plant.valve_limit": 5e-3}
    gains = np.array([(230.0, 230.0, 230.0)])
    j = {d: float(evaluate(gains, _cfg({**base, "plant.delay": d}))[0]) for d in (1, 2)}
    near1 = float(evaluate(gains, _cfg({**base, "plant.delay": 1, "plant.delay_fraction": 1e-9}))[0])
    near2 = float(evaluate(gains, _cfg({**base, "plant.delay": 1, "plant.delay_fraction": 1.0 - 1e-9}))[0])
    half = float(evaluate(gains, _cfg({**base, "plant.delay": 1, "plant.delay_fraction": 0.5}))[0])
    assert j[1] != j[2]
    assert near1 == pytest.approx(j[1], rel=1e-6) and near2 == pytest.approx(j[2], rel=1e-6)
    assert half not in (j[1], j[2])
    # the whole-sample delay is the fraction 0, bit for bit
    assert float(evaluate(gains, _cfg({**base, "plant.delay": 1, "plant.delay_fraction": 0.0}))[0]) == j[1]


def test_a_bad_fraction_is_refused_naming_the_key():
    for flat in ({"plant.delay_fraction": 1.0}, {"plant.delay_fraction": -0.1},
                 {"plant.delay": DELAY_MAX, "plant.delay_fraction": 0.5}):
        with pytest.raises(ConfigError, match="plant.delay_fraction"):
            build_config(flat, base=load_config())


def test_the_vouching_delay_variant_is_the_group_delay_it_stands_for_not_rounded():
    """At a 224 Hz band (the demo machine's) the lag at 448 Hz is 0.50 ms: 1.66 samples, not 2."""
    band = 224.0
    cfg = build_config({"plant.valve_frequency": 100.0, "plant.valve_limit": 5e-3, "plant.validated_band": band},
                       base=load_config())
    p = unseen_variants(cfg)[0].cfg.plant
    exact = 2.0 * UNSEEN_ZETA / (2.0 * np.pi * UNSEEN_FACTOR * band) / cfg.episode.step
    assert p.delay == 1 and p.delay + p.delay_fraction == pytest.approx(exact)
    # below one sample the variant keeps one whole sample (a lag the kernels' grid can show)
    high = build_config({"plant.validated_band": 2000.0}, base=load_config())
    p = unseen_variants(high)[0].cfg.plant
    assert (p.delay, p.delay_fraction) == (1, 0.0)
