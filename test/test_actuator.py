"""Physics of the plant model (SPEC §2, §5 step 6)."""
import dataclasses

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from has_control.core.actuator import derivative, plant_step, rk4_step
from has_control.core.params import Actuator


def leak_free_equilibrium(a: Actuator) -> np.ndarray:
    """Equal chamber pressures carrying the weight: no leakage flow, no net force."""
    p = a.mass * a.gravity / (a.area_cap - a.area_rod)
    return np.array([0.0, 0.0, p, p])


def test_equilibrium_is_a_fixed_point_of_the_plant():
    a = Actuator()
    ap = a.as_array()
    x = leak_free_equilibrium(a)
    d = derivative(*x, 0.0, ap)
    assert abs(d[0]) == 0.0
    assert abs(d[1]) < 1e-9            # m/s²: force balance to roundoff
    assert abs(d[2]) < 1e-3 and abs(d[3]) < 1e-3   # Pa/s, against pressures of 3 MPa
    for _ in range(3333):              # 1 s
        x = np.array(plant_step(*x, 0.0, ap, 3e-4))
    assert abs(x[0]) < 1e-12 and abs(x[1]) < 1e-12


def test_spec_initial_state_balances_the_weight():
    a = Actuator()
    x = a.initial_state()
    assert x[2] == pytest.approx(4.564e6, rel=1e-3)                 # SPEC §4: 4.564 MPa
    d = derivative(*x, 0.0, dataclasses.replace(a, leakage=0.0).as_array())
    assert abs(d[1]) < 1e-9 and d[2] == 0.0 and d[3] == 0.0


def _hydraulic_energy(a: Actuator, x0, x) -> float:
    """Kinetic + gravitational + compression energy for Ṗ = −βe·V̇/V (Bp = Ci = 0, u = 0).

    P(V) = P0 − βe·ln(V/V0), so the work stored is −∫P dV from V0 to V.
    """
    def chamber(p0, v0, v):
        return -(p0 * (v - v0) - a.bulk_modulus * (v * np.log(v / v0) - v + v0))
    v10 = a.volume_cap0 + a.area_cap * x0[0]
    v20 = a.volume_rod0 - a.area_rod * x0[0]
    v1 = a.volume_cap0 + a.area_cap * x[0]
    v2 = a.volume_rod0 - a.area_rod * x[0]
    return (0.5 * a.mass * x[1] ** 2 + a.mass * a.gravity * x[0]
            + chamber(x0[2], v10, v1) + chamber(x0[3], v20, v2))


def test_energy_is_conserved_without_damping_and_leakage():
    a = dataclasses.replace(Actuator(), damping=0.0, leakage=0.0)
    ap = a.as_array()
    x0 = a.initial_state()
    x0[1] = 0.05                                  # push it: 5 cm/s
    x = x0.copy()
    e0 = _hydraulic_energy(a, x0, x0)
    drift = 0.0
    for _ in range(3333):
        x = np.array(rk4_step(*x, 0.0, ap, 3e-4))
        drift = max(drift, abs(_hydraulic_energy(a, x0, x) - e0))
    # the motion exchanges ~1.9 J between kinetic and compression energy
    assert 0.5 * a.mass * 0.05 ** 2 == pytest.approx(1.875)
    assert drift < 1e-6 * 1.875


def test_damping_dissipates_energy_monotonically():
    a = dataclasses.replace(Actuator(), leakage=0.0)
    ap = a.as_array()
    x0 = a.initial_state()
    x0[1] = 0.05
    x = x0.copy()
    energies = [_hydraulic_energy(a, x0, x)]
    for _ in range(2000):
        x = np.array(rk4_step(*x, 0.0, ap, 3e-4))
        energies.append(_hydraulic_energy(a, x0, x))
    assert np.all(np.diff(energies) < 1e-9)
    assert energies[-1] < 0.5 * energies[0]


def _rk4_run(ap, x0, inputs, hold, steps_per_hold):
    h = hold / steps_per_hold
    x = np.array(x0, dtype=float)
    for u in inputs:
        for _ in range(steps_per_hold):
            x = np.array(rk4_step(*x, u, ap, h))
    return x


def test_rk4_global_error_is_fourth_order():
    """Halving Δt shrinks the error ~16× against a tight solve_ivp on the same ZOH input."""
    a = Actuator()
    ap = a.as_array()
    x0 = a.initial_state()
    hold = 2.4e-3
    inputs = 1e-4 * np.sin(0.35 * np.arange(60))       # changes sign: both valve edges, pressures stay interior
    ref = np.array(x0, dtype=float)
    for u in inputs:
        sol = solve_ivp(lambda t, x: derivative(*x, u, ap), (0.0, hold), ref,
                        method="DOP853", rtol=1e-13, atol=[1e-15, 1e-13, 1e-6, 1e-6])
        ref = sol.y[:, -1]
    scale = np.array([1e-3, 1e-2, 1e6, 1e6])           # m, m/s, Pa: comparable magnitudes
    errors = [np.max(np.abs(_rk4_run(ap, x0, inputs, hold, s) - ref) / scale) for s in (1, 2, 4)]
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    assert all(13.0 < r < 19.0 for r in ratios), (errors, ratios)


def test_pressures_stay_within_supply_and_return():
    a = Actuator()
    ap = a.as_array()
    for u in (0.05, -0.05):                            # absurdly large spool strokes
        x = a.initial_state()
        for _ in range(200):
            x = np.array(plant_step(*x, u, ap, 3e-4))
            assert a.return_pressure <= x[2] <= a.supply_pressure
            assert a.return_pressure <= x[3] <= a.supply_pressure
