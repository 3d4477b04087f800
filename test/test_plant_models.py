"""Model options of a real servo-hydraulic plant: a
second-order spool with its stop, a transport delay of the command, Coulomb
and Stribeck friction, RK4 substeps, quantised sensors and a derived
velocity. Each is checked against its physics or definition; every option
gives the same bits in the trace kernel and the batch kernel; the general
path with the options off is the reference path's arithmetic.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from has_control.common.errors import ConfigError
from has_control.config import build_config, load_config, with_horizon
from has_control.config.scenario_files import Scenario, load_scenarios
from has_control.core import episode as ep_mod
from has_control.core.actuator import friction_force, spool_plant_step, valve_plant_step
from has_control.core.episode import EpisodeArrays, _episode_general, evaluate, simulate
from has_control.core.noise import sensor_readings
from has_control.core.params import (
    N_SENSOR, RESOLUTION_P, RESOLUTION_Y, STRUCTURE, STRUCTURE_FULL, STRUCTURE_SPOOL, VELOCITY_ALPHA,
    VELOCITY_DERIVED, Config, Noise, Plant,
)
from has_control.identify.kernel import predict_segments
from has_control.wire import steps

MODEL = Config().actuator
X0 = tuple(MODEL.initial_state())
TUNED = (656.11, 656.13, 656.14)
MANUAL = (150.0, 158.0, 162.0)


def _cfg(flat: dict, horizon: float = 1.5) -> Config:
    return with_horizon(build_config(flat, base=load_config()), horizon)


def _spool_response(pp, u, dt, n):
    """The spool (xv, ẋv) under a held command u from rest, n steps of dt."""
    x, xv, wv = X0, 0.0, 0.0
    out = np.empty((n, 2))
    for k in range(n):
        *x, xv, wv = spool_plant_step(*x, xv, wv, u, pp, dt)
        out[k] = xv, wv
    return out


# --- second-order spool -----------------------------------------------------------------

@pytest.mark.parametrize("zeta", [0.3, 0.5])
def test_second_order_spool_step_has_its_overshoot_and_peak_time(zeta):
    """ẍv = ω²(u − xv) − 2ζω·ẋv from rest: overshoot e^(−ζπ/√(1−ζ²)), peak at π/(ω√(1−ζ²))."""
    fn, u, dt = 150.0, 1e-3, 1e-6
    om = 2 * math.pi * fn
    pp = Plant(valve_frequency=fn, valve_damping_ratio=zeta).as_array(MODEL)
    xv = _spool_response(pp, u, dt, 20000)[:, 0]
    k = int(np.argmax(xv))
    wd = om * math.sqrt(1 - zeta ** 2)
    assert (xv[k] - u) / u == pytest.approx(math.exp(-zeta * math.pi / math.sqrt(1 - zeta ** 2)), rel=1e-6)
    assert (k + 1) * dt == pytest.approx(math.pi / wd, abs=1.5 * dt)


def test_second_order_spool_is_the_first_order_lag_2_zeta_over_omega_at_low_frequency():
    """At f ≪ f_n, ω²/(s² + 2ζωs + ω²) ≈ 1/(1 + τs), τ = 2ζ/ω: the two spools differ by O((f/f_n)²)."""
    fn, zeta, dt, f = 150.0, 0.7, 1e-5, 5.0
    om = 2 * math.pi * fn
    second = Plant(valve_frequency=fn, valve_damping_ratio=zeta).as_array(MODEL)
    first = Plant(valve_time_constant=2 * zeta / om).as_array(MODEL)
    first[STRUCTURE] = STRUCTURE_SPOOL
    amp = 1e-3
    x2 = x1 = X0
    s2 = w2 = s1 = w1 = 0.0
    worst_gap = worst_lag = 0.0
    for k in range(40000):
        u = amp * math.sin(2 * math.pi * f * k * dt)
        *x2, s2, w2 = spool_plant_step(*x2, s2, w2, u, second, dt)
        *x1, s1, w1 = spool_plant_step(*x1, s1, w1, u, first, dt)
        if k > 20000:                                        # past the transient (5 time constants ≪ 0.2 s)
            worst_gap = max(worst_gap, abs(s2 - s1))
            worst_lag = max(worst_lag, abs(s1 - amp * math.sin(2 * math.pi * f * (k + 1) * dt)))
    assert worst_lag > 0.03 * amp                             # the lag is seen: ωτ ≈ 0.047
    assert worst_gap < 0.005 * amp                            # (f/f_n)² ≈ 0.0011


def test_the_second_order_spool_is_held_at_its_stop():
    """With a travel limit an underdamped spool driven to the limit stops there, its velocity zeroed."""
    limit = 2e-3
    pp = Plant(valve_frequency=150.0, valve_damping_ratio=0.2, valve_limit=limit).as_array(MODEL)
    r = _spool_response(pp, 9e-3, 1e-5, 3000)             # the command clipped to the limit first
    assert np.max(np.abs(r[:, 0])) == limit
    at_stop = r[:, 0] == limit
    assert at_stop.any() and np.all(r[at_stop, 1] == 0.0)
    free = Plant(valve_frequency=150.0, valve_damping_ratio=0.2, valve_limit=0.0).as_array(MODEL)
    assert np.max(_spool_response(free, 2e-3, 1e-5, 3000)[:, 0]) > 1.4 * limit   # it would overshoot


def test_the_general_path_with_the_options_off_is_the_reference_arithmetic():
    """spool_plant_step of an ideal or first-order valve, and the general episode kernel
    forced on a reference plant, give the reference path's bits."""
    x = (0.01, 0.05, 5.0e6, 8.0e6)
    for plant in (Plant(), Plant(valve_time_constant=1e-3, valve_limit=3e-3)):
        pp = plant.as_array(MODEL)
        general = pp.copy()
        general[STRUCTURE] = STRUCTURE_SPOOL
        for u in (-4e-3, 0.0, 1.5e-3):
            assert spool_plant_step(*x, 2e-4, 0.0, u, general, 3e-4)[:5] == valve_plant_step(*x, 2e-4, u, pp, 3e-4)
        cfg = _cfg({"plant.valve_time_constant": plant.valve_time_constant, "plant.valve_limit": plant.valve_limit,
                    "noise.position": 1e-6, "noise.seed": 3}, 1.5)
        arr = EpisodeArrays.from_config(cfg)
        ref = simulate(cfg, TUNED)
        forced = arr.plant.copy()
        forced[STRUCTURE] = STRUCTURE_SPOOL
        trace = np.zeros((cfg.episode.samples, len(ep_mod.TRACE_COLUMNS)))
        out = _episode_general(*TUNED, arr.actuator, forced, arr.adaptation, arr.reference, arr.sensor,
                               arr.seed, arr.episode, arr.x0, trace)
        np.testing.assert_array_equal(trace, ref.data)
        assert out[0] == ref.score.J


# --- transport delay ---------------------------------------------------------------------

@pytest.mark.parametrize("d", [1, 5, 16])
def test_a_delay_applies_the_command_of_d_samples_earlier(d):
    """predict_segments with delay d on commands u equals delay 0 on u shifted by d (zeros first)."""
    rng = np.random.default_rng(1)
    n = 400
    u = rng.uniform(-2e-3, 2e-3, n)
    x0 = np.array([X0, X0])
    starts = np.array([0, 200])
    base = {"valve_frequency": 120.0, "valve_limit": 3e-3}
    delayed = Plant(delay=d, **base).as_array(MODEL)
    prompt = Plant(**base).as_array(MODEL)
    a = np.zeros((2, 151, 4))
    b = np.zeros((2, 151, 4))
    predict_segments(delayed, 3e-4, x0, u, starts, 150, a)
    predict_segments(prompt, 3e-4, x0, np.r_[np.zeros(d), u[:-d]], starts, 150, b)
    np.testing.assert_array_equal(a, b)
    c = np.zeros((2, 151, 4))
    predict_segments(prompt, 3e-4, x0, u, starts, 150, c)
    assert not np.array_equal(a, c)


def test_the_plant_node_kernel_delays_as_the_library():
    """steps.plant_sample, fed the library trace's commands, steps the trace's states bit for bit."""
    cfg = _cfg({"plant.delay": 4, "plant.valve_frequency": 180.0, "plant.valve_limit": 4e-3,
                "plant.friction_coulomb": 200.0, "plant.friction_stribeck": 300.0, "plant.substeps": 2}, 1.5)
    tr = simulate(cfg, MANUAL)
    np.testing.assert_array_equal(node_step_states(cfg, tr["u"]), tr.data[:, 2:6])


def node_step_states(cfg, u) -> np.ndarray:
    """The states [y, v, pa, pb] the plant node's kernel (steps.plant_sample) passes through, fed the commands ``u``."""
    arr = EpisodeArrays.from_config(cfg)
    x = steps.plant_state(arr.x0)
    state, clock, scr = steps.STATE_LAYOUT.buffer(), steps.CLOCK_LAYOUT.buffer(), steps.scratch()
    states = np.empty((len(u), 4))
    for i in range(len(u)):
        states[i] = x[:4]
        steps.plant_sample(x, u[i], arr.plant, cfg.episode.step, cfg.episode.y_limit, i + 1,
                           cfg.episode.step_ns, state, clock, scr)
    return states


# --- friction ------------------------------------------------------------------------------

def _closed_valve_run(plant: Plant, x0, n=400, dt=3e-4):
    pp = plant.as_array(dataclasses.replace(MODEL, damping=0.0, leakage=0.0))
    x, xv, wv = tuple(x0), 0.0, 0.0
    v = np.empty(n)
    for k in range(n):
        *x, xv, wv = spool_plant_step(*x, xv, wv, 0.0, pp, dt)
        v[k] = x[1]
    return v


def test_friction_opposes_motion_and_is_smooth_through_zero():
    pp = Plant(friction_coulomb=250.0, friction_stribeck=400.0, stribeck_velocity=0.01,
               friction_smoothing=1e-4).as_array(MODEL)
    for v in (-0.3, -1e-3, 1e-5, 0.02, 1.0):
        assert friction_force(v, pp) * v > 0.0
    assert friction_force(0.0, pp) == 0.0
    stribeck = 250.0 + 150.0 * math.exp(-0.01)                       # near Fs at v = v_s/10
    assert friction_force(1e-3, pp) == pytest.approx(stribeck / math.sqrt(1.0 + 0.01), rel=1e-12)
    assert friction_force(1.0, pp) == pytest.approx(250.0, rel=1e-6)                                 # Fc


def test_static_friction_above_the_net_force_holds_the_piston():
    """A 200 N imbalance (P1 raised) rings the oil column; 2 kN of static friction holds it (creep ~ε·ΔF/Fs)."""
    x0 = np.array(X0)
    x0[2] += 200.0 / MODEL.area_cap
    free = _closed_valve_run(Plant(substeps=20), x0)
    held = _closed_valve_run(Plant(friction_coulomb=1800.0, friction_stribeck=2000.0, substeps=20), x0)
    assert np.max(np.abs(free)) > 5e-4
    assert np.max(np.abs(held)) < 0.02 * np.max(np.abs(free))


def test_friction_dissipates_the_oil_spring_oscillation():
    """Closed valve, no damping or leakage, the piston started at 10 mm/s: the oil spring keeps the
    oscillation's amplitude without friction; Coulomb friction takes its energy."""
    x0 = np.array(X0)
    x0[1] = 0.01
    free = _closed_valve_run(Plant(substeps=4), x0, n=1000)
    rubbing = _closed_valve_run(Plant(friction_coulomb=300.0, friction_stribeck=300.0, substeps=4), x0, n=1000)
    assert np.max(np.abs(free[-300:])) > 0.97 * 0.01
    assert np.max(np.abs(rubbing[-300:])) < 0.5 * 0.01


# --- substeps -----------------------------------------------------------------------------

def test_substeps_converge_at_fourth_order():
    """One 3 ms sample, valve open: the error against 256 substeps falls ~16x per halved substep."""
    x = (0.0, 0.02, 6.0e6, 9.0e6)
    u, dt = 1.0e-3, 3e-3

    def step(n):
        pp = Plant(substeps=n, valve_frequency=100.0, valve_damping_ratio=0.7).as_array(MODEL)
        pp[STRUCTURE] = STRUCTURE_FULL
        return np.array(spool_plant_step(*x, 0.0, 0.0, u, pp, dt)[:4])
    exact = step(256)
    scale = np.abs(exact - np.array(x))
    errors = [np.max(np.abs(step(n) - exact) / scale) for n in (4, 8, 16)]
    for coarse, fine in zip(errors, errors[1:]):
        assert 12.0 < coarse / fine < 20.0, errors


def test_one_substep_is_the_reference_step():
    """substeps = 1 in the full structure is the spool structure's single step, bit for bit."""
    x = (0.01, 0.05, 5.0e6, 8.0e6)
    pp = Plant(valve_frequency=150.0, valve_limit=3e-3).as_array(MODEL)
    full = pp.copy()
    full[STRUCTURE] = STRUCTURE_FULL
    for u in (-4e-3, 1e-3):
        assert spool_plant_step(*x, 1e-3, 0.2, u, full, 3e-4) == spool_plant_step(*x, 1e-3, 0.2, u, pp, 3e-4)


# --- sensors --------------------------------------------------------------------------------

def _readings(y, sp, dt=3e-4):
    out = np.empty((len(y), 4))
    yp = vp = 0.0
    for i, yi in enumerate(y):
        out[i] = sensor_readings(yi, 0.1, 5e6, 6e6, 0.0, 0.0, 0.0, 0.0, False, sp, yp, vp, i > 0, dt)
        yp, vp = out[i, 0], out[i, 1]
    return out


def test_quantised_readings_lie_on_the_grid_nearest_the_value():
    sp = np.zeros(N_SENSOR)
    sp[RESOLUTION_Y], sp[RESOLUTION_P] = 1e-6, 5e3
    y = np.linspace(-3e-5, 4e-5, 301)
    r = _readings(y, sp)
    k = r[:, 0] / 1e-6
    assert np.all(np.abs(k - np.round(k)) < 1e-9) and np.all(np.abs(r[:, 0] - y) <= 0.5e-6 * (1 + 1e-12))
    assert r[0, 2] == 5e6 and r[0, 3] == 6e6 and r[0, 1] == 0.1     # on the grid already; velocity measured


def test_derived_velocity_is_the_backward_difference_and_its_filter_a_first_order_lag():
    dt = 3e-4
    y = 1e-3 * np.sin(np.arange(500) * dt * 7.0) + 1e-6 * np.random.default_rng(2).standard_normal(500)
    sp = np.zeros(N_SENSOR)
    sp[VELOCITY_DERIVED] = 1.0                                   # α = 0: unfiltered
    r = _readings(y, sp, dt)
    assert r[0, 1] == 0.0
    np.testing.assert_array_equal(r[1:, 1], (y[1:] - y[:-1]) / dt)
    alpha = Noise(velocity_filter_frequency=100.0).as_array(dt)[VELOCITY_ALPHA]
    assert alpha == pytest.approx(1 - math.exp(-2 * math.pi * 100.0 * dt))
    sp[VELOCITY_ALPHA] = alpha
    f = _readings(y, sp, dt)[:, 1]
    expect = np.zeros(500)
    for i in range(1, 500):
        expect[i] = expect[i - 1] + alpha * (r[i, 1] - expect[i - 1])
    np.testing.assert_allclose(f, expect, rtol=1e-12, atol=1e-15)
    assert np.std(np.diff(f)) < 0.5 * np.std(np.diff(r[:, 1]))          # it smooths the noise's differences


def test_the_controller_reads_the_sensors_and_the_cost_the_true_state():
    quiet = simulate(_cfg({}), MANUAL)
    coarse = simulate(_cfg({"noise.position_resolution": 2e-6, "noise.pressure_resolution": 1e4,
                            "noise.velocity_source": "derived", "noise.velocity_filter_frequency": 300.0}), MANUAL)
    assert not np.array_equal(coarse["u"], quiet["u"]) and np.isfinite(coarse.score.J)
    np.testing.assert_array_equal(coarse["e1"], coarse["x1d"] - coarse["y"])


# --- the trace and the batch kernel agree --------------------------------------------------------

CASES = {
    "second-order": {"plant.valve_frequency": 150.0, "plant.valve_damping_ratio": 0.7, "plant.valve_limit": 5e-3},
    "delay": {"plant.delay": 3},
    "spool+delay+noise": {"plant.valve_frequency": 120.0, "plant.delay": 2, "noise.position": 1e-6,
                          "noise.pressure_cap": 1e4, "noise.seed": 4},
    "friction": {"plant.friction_coulomb": 250.0, "plant.friction_stribeck": 400.0},
    "substeps": {"plant.substeps": 3, "plant.valve_time_constant": 1e-3},
    "sensors": {"noise.position_resolution": 1e-6, "noise.pressure_resolution": 5e3,
                "noise.velocity_source": "derived", "noise.velocity_filter_frequency": 200.0},
    "everything, backward x3d": {"plant.valve_frequency": 100.0, "plant.valve_limit": 4e-3, "plant.delay": 1,
                                 "plant.friction_coulomb": 250.0, "plant.friction_stribeck": 450.0,
                                 "plant.substeps": 2, "noise.position": 1e-6, "noise.seed": 9,
                                 "noise.position_resolution": 1e-6, "noise.velocity_source": "derived",
                                 "adaptation.x3d_derivative": "backward_difference"},
}


@pytest.mark.parametrize("name", list(CASES))
def test_every_option_gives_the_same_bits_in_the_trace_and_the_batch(name):
    cfg = _cfg(CASES[name], 1.5)
    gains = np.array([MANUAL, TUNED, (300.0, 250.0, 400.0)])
    batch = evaluate(gains, cfg, metrics=True)
    for g, row in zip(gains, batch):
        s = simulate(cfg, tuple(g)).score
        np.testing.assert_array_equal(row, [s.J, s.e_max, s.e_mu, s.e_sigma])
    assert not np.array_equal(batch, evaluate(gains, _cfg({}, 1.5), metrics=True))   # the option acts


# --- configuration ---------------------------------------------------------------------------------

@pytest.mark.parametrize("flat,culprit", [
    ({"plant.delay": 17}, "plant.delay = 17"),
    ({"plant.delay": 1.5}, "plant.delay = 1.5"),
    ({"plant.substeps": 0}, "plant.substeps = 0"),
    ({"plant.valve_frequency": 150.0, "plant.valve_time_constant": 1e-3}, "plant.valve_frequency"),
    ({"plant.valve_frequency": 5000.0}, "plant.valve_frequency = 5000"),
    ({"plant.valve_damping_ratio": 0.0}, "plant.valve_damping_ratio"),
    ({"plant.friction_coulomb": -1.0}, "plant.friction_coulomb"),
    ({"plant.stribeck_velocity": 0.0}, "plant.stribeck_velocity"),
    ({"noise.velocity_source": "guessed"}, "noise.velocity_source"),
    ({"noise.position_resolution": -1e-6}, "noise.position_resolution"),
])
def test_bad_model_options_are_one_line_naming_the_key(flat, culprit):
    with pytest.raises(ConfigError) as err:
        build_config(flat, source="f.yaml")
    msg = str(err.value)
    assert "\n" not in msg and culprit in msg and msg.startswith("f.yaml: ")


def test_the_shipped_files_are_the_reference_and_scenarios_take_the_new_keys():
    assert load_config().plant == Plant() and load_config().noise == Noise()
    assert not Noise().as_array().any()                          # the reference's sensor array is all zeros
    assert Plant().structure() == 0
    cfg = Scenario("real", (("plant.delay", 2), ("plant.valve_frequency", 100.0),
                            ("noise.velocity_source", "derived"))).config(Config())
    assert cfg.plant.delay == 2 and cfg.plant.valve_frequency == 100.0 and cfg.noise.velocity_source == "derived"
    assert cfg.plant.structure() == STRUCTURE_SPOOL


def test_a_scenario_file_draws_whole_delays_and_substeps(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text("scenarios:\n  late: {plant.delay: 3, plant.valve_frequency: 120.0}\n"
                 "random:\n  count: 12\n  seed: 2\n  ranges: {plant.delay: [0, 4], plant.substeps: [1, 3]}\n"
                 "  set: {plant.friction_coulomb: 200.0}\n")
    scen = load_scenarios(f)
    cfgs = [s.config(Config()) for s in scen]
    assert cfgs[0].plant.delay == 3 and cfgs[0].plant.valve_frequency == 120.0
    delays = {c.plant.delay for c in cfgs[1:]}
    assert all(isinstance(c.plant.delay, int) and isinstance(c.plant.substeps, int) for c in cfgs)
    assert delays <= set(range(5)) and len(delays) > 1 and all(c.plant.friction_coulomb == 200.0 for c in cfgs[1:])


# --- graph = library ---------------------------------------------------------------------------------

@pytest.mark.ros
@pytest.mark.parametrize("added_by", ["controller", "plant"])
def test_graph_equals_the_library_with_the_model_options(context, added_by):
    from has_control.nodes.stack import run_stack
    cfg = _cfg({**CASES["everything, backward x3d"], "noise.added_by": added_by}, 1.5)
    ref = simulate(cfg, MANUAL)
    run = run_stack(cfg, gains=MANUAL, context=context)
    np.testing.assert_array_equal(run.trace, ref.data)
    assert run.score == ref.score
