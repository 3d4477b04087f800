"""Identification reads its predictions through the sensors the user declared:
a velocity differentiated from position (``noise.velocity_source: derived``)
is compared with the predicted position's own filtered difference, and a
segment starts from the position's slope, not from the lagging reading.
Without it a machine's Coulomb friction lost to viscous damping on BIC
(docs/findings.md, drawn-4)."""
import numpy as np

from has_control.config import CONFIG_DIR, build_config, load_config
from has_control.core.episode import simulate
from has_control.identify.data import experiment_from_trace
from has_control.identify.fit import as_read, initial_states
from has_control.identify.structures import Structure, _lag_start, fit_structure
from has_control.identify.verdict import noise_levels

DERIVED = {"noise.velocity_source": "derived", "noise.velocity_filter_frequency": 200.0}


def _experiment(extra: dict, horizon: float = 10.0):
    cfg = build_config({**DERIVED, "simulation.horizon": horizon, **extra}, source="test",
                       base=load_config([CONFIG_DIR / "identify.yaml"]))
    trace = simulate(cfg)
    truth = np.column_stack([trace["y"], trace["ydot"], trace["P1"], trace["P2"]])
    return experiment_from_trace(trace, cfg), truth


def test_the_true_states_read_through_the_declared_sensors_are_the_readings():
    exp, truth = _experiment({}, horizon=2.0)               # no noise, no quantisation: readings are exact
    s = np.array([100, 900, 2500])
    pred = truth[s[:, None] + np.arange(97)]
    read = as_read(pred.copy(), exp, s)
    np.testing.assert_allclose(read[:, :, 1], exp.x[s[:, None] + np.arange(97), 1], rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(read[:, :, [0, 2, 3]], pred[:, :, [0, 2, 3]])
    # the reading lags: at the start of a fast segment the slope is nearer the true velocity than the reading
    x0 = initial_states(exp, s)
    assert np.all(np.abs(x0[:, 1] - truth[s, 1]) < np.abs(exp.x[s, 1] - truth[s, 1]))


def test_friction_seen_through_a_derived_velocity_is_identified():
    friction = {"plant.friction_coulomb": 200.0, "noise.position": 1e-6, "noise.pressure_cap": 1e4,
                "noise.pressure_rod": 1e4, "noise.added_by": "plant", "noise.seed": 3}
    exp, _ = _experiment(friction)
    exps = [exp]
    sigma = np.sqrt(np.mean([noise_levels(e.x) ** 2 for e in exps], axis=0))
    tau = _lag_start(exps)
    without = fit_structure(exps, Structure("ideal", 0, False), sigma, tau)
    with_friction = fit_structure(exps, Structure("ideal", 0, True), sigma, tau)
    assert with_friction.bic < without.bic - 10.0
    # its residuals are the sensors' noise (read through the lagging reading, they were not: y not white)
    assert with_friction.result.verdict.adequate, with_friction.result.verdict.line()
    est = with_friction.result.estimates
    assert abs(est["friction_coulomb"].value - 200.0) < 0.15 * 200.0
    damping = load_config().actuator.damping                  # the plant's (no override)
    assert abs(est["damping"].value - damping) < 0.1 * damping
