"""The plant beside the controller's model: mismatch, valve limit and lag,
measurement noise and the road reference.

Each option is checked against its physics or its definition, the reference
configuration against itself (an option at its default changes no bit), and
a graph run with every option on against the library's trace.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from has_control.core import noise
from has_control.core.actuator import derivative, plant_step, valve_plant_step
from has_control.config import build_config, load_config
from has_control.core.cost import score_arrays
from has_control.core.episode import EpisodeArrays, evaluate, simulate
from has_control.config import with_horizon
from has_control.common.errors import ConfigError
from has_control.core.params import Config, Episode, Plant, Reference
from has_control.core.reference import reference, reference_array
from has_control.core.road import road_rms, road_table

OPTIONS = {"plant.mass": 1650.0, "plant.bulk_modulus": 6.0e8, "plant.leakage": 1.0e-12,
           "plant.supply_pressure": 1.7e7, "plant.valve_limit": 4.0e-3, "plant.valve_time_constant": 1.0e-3,
           "noise.position": 2.0e-6, "noise.velocity": 1.0e-4, "noise.pressure_cap": 2.0e4,
           "noise.pressure_rod": 2.0e4, "noise.seed": 11}


def _cfg(flat: dict, horizon: float = 1.5) -> Config:
    return with_horizon(build_config(flat, base=load_config()), horizon)


# --- the reference configuration is untouched -----------------------------------------

def test_options_at_their_defaults_change_no_bit():
    """Overrides equal to the model, an unlimited ideal valve and zero noise are the reference configuration."""
    base = with_horizon(Config(), 2.0)
    a = base.actuator
    same = _cfg({"plant.mass": a.mass, "plant.bulk_modulus": a.bulk_modulus, "plant.damping": a.damping,
                 "plant.leakage": a.leakage, "plant.supply_pressure": a.supply_pressure,
                 "plant.valve_gain": a.valve_gain, "plant.valve_limit": 0.0, "plant.valve_time_constant": 0.0,
                 "noise.seed": 5}, 2.0)
    gains = np.array([[150.0, 158.0, 162.0], [656.11, 656.13, 656.14], [900.0, 300.0, 700.0]])
    np.testing.assert_array_equal(evaluate(gains, same, metrics=True), evaluate(gains, base, metrics=True))
    np.testing.assert_array_equal(simulate(same).data, simulate(base).data)


def test_the_valve_step_without_limit_or_lag_is_the_plant_step():
    ap = Config().actuator.as_array()
    pp = Plant().as_array(Config().actuator)
    x = (0.01, 0.05, 5.0e6, 8.0e6)
    for u in (-2e-3, 0.0, 1.5e-3):
        assert valve_plant_step(*x, 123.0, u, pp, 3e-4)[:4] == plant_step(*x, u, ap, 3e-4)


# --- mismatch ----------------------------------------------------------------------------

def test_a_mismatched_plant_starts_at_its_own_equilibrium_and_changes_the_run():
    cfg = _cfg({"plant.mass": 1800.0, "plant.supply_pressure": 1.6e7})
    arr = EpisodeArrays.from_config(cfg)
    rates = derivative(*arr.x0, 0.0, arr.plant)
    assert rates[1] == pytest.approx(0.0, abs=1e-12)          # at rest: the force balance of the true mass
    assert arr.x0[3] == 0.8e7 and arr.actuator[0] == 1500.0    # P2 = Ps/2 of the plant; the model keeps its mass
    assert simulate(cfg).score.J != simulate(_cfg({})).score.J


# --- valve limit and lag -------------------------------------------------------------------

def test_a_command_beyond_the_travel_limit_acts_as_the_limit():
    pp = Plant(valve_limit=2e-3).as_array(Config().actuator)
    x = (0.0, 0.0, 5.0e6, 8.0e6)
    assert valve_plant_step(*x, 0.0, 9e-3, pp, 3e-4) == valve_plant_step(*x, 0.0, 2e-3, pp, 3e-4)
    assert valve_plant_step(*x, 0.0, -9e-3, pp, 3e-4) == valve_plant_step(*x, 0.0, -2e-3, pp, 3e-4)
    assert valve_plant_step(*x, 0.0, 1e-3, pp, 3e-4) != valve_plant_step(*x, 0.0, 2e-3, pp, 3e-4)


def test_the_spool_follows_a_held_command_as_a_first_order_lag_to_fourth_order():
    """τ·ẋv = u − xv from xv = 0: xv(t) = u·(1 − e^(−t/τ)); RK4's error shrinks 16-fold per halved step."""
    tau, u, t_end = 5e-3, 1e-3, 0.02
    errors = []
    for dt in (1e-3, 5e-4, 2.5e-4):
        pp = Plant(valve_time_constant=tau).as_array(Config().actuator)
        x = tuple(Config().actuator.initial_state())
        xv = 0.0
        for _ in range(int(round(t_end / dt))):
            *x, xv = valve_plant_step(*x, xv, u, pp, dt)
        errors.append(abs(xv - u * (1.0 - math.exp(-t_end / tau))))
    assert errors[0] < 1e-8
    for coarse, fine in zip(errors, errors[1:]):
        assert 12.0 < coarse / fine < 20.0, errors


def test_an_unmodelled_valve_lag_costs_tracking_and_destabilises_high_gains():
    """The law assumes an ideal valve: a lag it does not know of costs accuracy,
    and at a few milliseconds it destabilises the paper's high gains (k ≈ 656)
    while the manual ones (k ≈ 155), of lower bandwidth, still track."""
    tuned, manual = (656.11, 656.13, 656.14), (150.0, 158.0, 162.0)
    ideal = simulate(_cfg({}), tuned).score
    lagged = simulate(_cfg({"plant.valve_time_constant": 1e-3}), tuned).score
    assert np.isfinite(lagged.J) and lagged.e_max > ideal.e_max
    slow = _cfg({"plant.valve_time_constant": 5e-3}, 3.0)
    assert simulate(slow, tuned).score.diverged and not simulate(slow, manual).score.diverged


# --- measurement noise ------------------------------------------------------------------------

def _uniform_reference(seed: int, i: int, k: int) -> float:
    """An independent implementation (Python integers modulo 2^64) of noise.uniform."""
    mask = (1 << 64) - 1

    def mix(z):
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
        return z ^ (z >> 31)
    golden = 0x9E3779B97F4A7C15
    key = mix((seed * golden + 1) & mask)
    h = mix(key ^ (((4 * i + k) * golden) & mask))
    return ((h >> 11) + 1) * 2.0 ** -53


@pytest.mark.parametrize("seed,i,k", [(0, 0, 0), (11, 5, 3), (2**62 + 7, 33332, 1), (1, 10**9, 2)])
def test_noise_uniforms_equal_an_independent_implementation(seed, i, k):
    assert noise.uniform(seed, i, k) == _uniform_reference(seed, i, k)


def test_noise_is_standard_normal_uncorrelated_and_seeded():
    sp = np.ones(4)
    z = np.array([noise.measurement_noise(sp, 3, i) for i in range(40000)])
    assert np.all(np.abs(z.mean(axis=0)) < 0.03) and np.all(np.abs(z.std(axis=0) - 1.0) < 0.03)
    c = np.corrcoef(np.c_[z[1:], z[:-1]].T)
    assert np.max(np.abs(c - np.eye(8))) < 0.03                  # across channels and from sample to sample
    assert noise.measurement_noise(sp, 3, 7) == noise.measurement_noise(sp, 3, 7)
    assert noise.measurement_noise(sp, 4, 7) != noise.measurement_noise(sp, 3, 7)


def test_the_controller_reads_noise_and_the_cost_scores_the_true_error():
    quiet = simulate(_cfg({}))
    noisy = simulate(_cfg({"noise.position": 5e-6, "noise.pressure_cap": 5e4, "noise.seed": 2}))
    assert not np.array_equal(noisy["u"], quiet["u"])
    np.testing.assert_array_equal(noisy["e1"], noisy["x1d"] - noisy["y"])      # the true error
    again = score_arrays(noisy["e1"], noisy["u"], _cfg({}).episode.as_array())
    assert (again.J, again.e_max, again.e_mu, again.e_sigma) == (
        noisy.score.J, noisy.score.e_max, noisy.score.e_mu, noisy.score.e_sigma)


# --- road reference ---------------------------------------------------------------------------

def test_road_profile_has_its_class_power_its_derivatives_and_repeats():
    ep = Episode(horizon=10.0)
    c = Reference(kind="road", road_class="C", speed=20.0, cutoff=2.0, seed=4, offset=0.01)
    table = road_table(c, ep)
    assert table[0, 0] == 0.01                                   # starts where the actuator rests (offset)
    assert np.std(table[:, 0]) == pytest.approx(road_rms(c, ep), rel=1e-6)   # whole periods: the sum's power
    d = Reference(kind="road", road_class="D", speed=20.0, cutoff=2.0, seed=4)
    assert road_rms(d, ep) == pytest.approx(2.0 * road_rms(c, ep), rel=1e-12)   # Gd(n0) x 4: amplitude x 2
    dt = ep.step
    for order in range(3):                                       # central differences of each column
        fd = (table[2:, order] - table[:-2, order]) / (2 * dt)
        scale = np.max(np.abs(table[:, order + 1]))
        assert np.max(np.abs(fd - table[1:-1, order + 1])) < 1e-3 * scale
    rp = reference_array(c, ep)
    assert reference(rp, 17 * dt) == reference(rp, (17 + ep.samples) * dt) == tuple(table[17])


def test_road_episode_tracks_a_road():
    cfg = _cfg({"reference.kind": "road", "reference.road_class": "D", "reference.seed": 3}, 3.0)
    s = simulate(cfg, (656.11, 656.13, 656.14)).score
    assert np.isfinite(s.J) and s.e_max < 1e-3


# --- bad input ----------------------------------------------------------------------------------

@pytest.mark.parametrize("flat,culprit", [
    ({"plant.valve_time_constant": 1e-5}, "plant.valve_time_constant"),
    ({"plant.mass": -1.0}, "plant.mass"),
    ({"plant.masss": 1.0}, "plant.masss: unknown parameter"),
    ({"noise.seed": -1}, "noise.seed"),
    ({"noise.position": math.nan}, "noise.position"),
    ({"reference.kind": "road", "reference.cutoff": 0.05}, "reference.cutoff"),
    ({"reference.road_class": "F"}, "reference.road_class"),
    ({"plant.supply_pressure": 1.0, "actuator.return_pressure": 2.0}, "plant.supply_pressure"),
])
def test_bad_plant_options_are_one_line_naming_the_key(flat, culprit):
    with pytest.raises(ConfigError) as err:
        build_config(flat, source="f.yaml")
    msg = str(err.value)
    assert "\n" not in msg and culprit in msg and msg.startswith("f.yaml: ")


# --- graph = library ------------------------------------------------------------------------------

@pytest.mark.ros
def test_graph_equals_the_library_with_mismatch_limit_lag_and_noise(context, tmp_path):
    from has_control.bag import score_bag
    from has_control.nodes.stack import run_stack
    cfg = _cfg({**OPTIONS, "reference.kind": "road", "reference.road_class": "D", "reference.seed": 2}, 1.5)
    gains = (656.11, 656.13, 656.14)
    ref = simulate(cfg, gains)
    run = run_stack(cfg, gains=gains, context=context, record=tmp_path / "bag")
    assert run.trace.shape == ref.data.shape == (5000, 12)
    np.testing.assert_array_equal(run.trace, ref.data)
    assert run.score == ref.score and run.failsafe_events == 0
    score, _ = score_bag(run.bag)                               # the bag keeps the true state
    assert (score.J, score.e_max, score.e_mu, score.e_sigma) == (ref.score.J, ref.score.e_max, ref.score.e_mu,
                                                                 ref.score.e_sigma)
