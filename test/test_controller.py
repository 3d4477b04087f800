"""The adaptive back-stepping law (SPEC §3): projection, sign of u, Lyapunov decrease."""
import dataclasses
import math

import numpy as np
import pytest

from has_control.core.abc_controller import abc_law, adapt, projection
from has_control.core.episode import simulate
from has_control.core.params import Actuator, Adaptation, Config, Reference


def test_projection_stops_only_outward_motion_at_the_bounds():
    assert projection(3000.0, 5.0, 2600.0, 3000.0) == 0.0     # at max, pushing up
    assert projection(3000.0, -5.0, 2600.0, 3000.0) == -5.0   # at max, coming back
    assert projection(2600.0, -5.0, 2600.0, 3000.0) == 0.0    # at min, pushing down
    assert projection(2600.0, 5.0, 2600.0, 3000.0) == 5.0
    assert projection(2800.0, -5.0, 2600.0, 3000.0) == -5.0   # inside: untouched


def test_adaptation_keeps_estimates_within_bounds():
    cp = Adaptation().as_array()
    a1, a2 = 2999.9, 9.99e-12
    for rate in (1e9, -1e9, 1e9):
        a1, a2 = adapt(a1, a2, rate, rate * 1e-20, cp, 3e-4)
        assert 2600.0 <= a1 <= 3000.0 and 4e-12 <= a2 <= 1e-11
    tr = simulate(Config(), (656.11, 656.13, 656.14))
    assert np.all((tr["a1_hat"] >= 2600.0) & (tr["a1_hat"] <= 3000.0))
    assert np.all((tr["a2_hat"] >= 4e-12) & (tr["a2_hat"] <= 1e-11))


def _law(x, k=(150.0, 158.0, 162.0), ref=(0.0, 0.0, 0.0, 0.0), a=Actuator()):
    ap = a.as_array()
    cp = Adaptation().as_array()
    return abc_law(*x, 2600.0, 4e-12, 0.0, True, *ref, *k, ap, cp, 3e-4)


@pytest.mark.parametrize("y_offset", [-0.01, -0.001, 0.001, 0.01])
def test_sign_of_u_follows_the_numerator_and_uses_the_matching_valve_edge(y_offset):
    """u = N/b3 with E1, E2 of the valve edge that sign(N) opens (SPEC §3)."""
    a = Actuator()
    x = a.initial_state()
    x[0] = y_offset
    u, e1, e2, e3, r1, r2, x3d = _law(x)
    ap = a
    v1 = a.volume_cap0 + a.area_cap * x[0]
    v2 = a.volume_rod0 - a.area_rod * x[0]
    # y below the reference (e1 > 0) must open the valve to extend: u > 0
    assert np.sign(u) == np.sign(-y_offset)
    if u >= 0:
        e_1, e_2 = math.sqrt(a.supply_pressure - x[2]), math.sqrt(x[3] - a.return_pressure)
    else:
        e_1, e_2 = math.sqrt(x[2] - a.return_pressure), math.sqrt(a.supply_pressure - x[3])
    b3 = (a.area_cap * e_1 / v1 + a.area_rod * e_2 / v2) * ap.valve_gain * ap.bulk_modulus
    f = a.area_cap * x[2] - a.area_rod * x[3]
    hu = (a.area_cap / v1 + a.area_rod / v2) * (x[2] - x[3]) * a.bulk_modulus
    gc = 0.0
    v_hat = (f - a.mass * a.gravity) / a.mass
    dx2d = 150.0 * (0.0 - 0.0)
    de1 = 0.0
    ddx2d = 150.0 * (0.0 - v_hat)
    dx3d = a.mass * 158.0 * (dx2d - v_hat) + a.mass * de1 + a.mass * ddx2d
    n = 162.0 * e3 + gc + 4e-12 * hu + dx3d + e2 / a.mass
    assert u == pytest.approx(n / b3, rel=1e-12)


def test_u_is_zero_when_b3_vanishes():
    a = Actuator()
    # both chambers at the limits the opening edge would need: Ps - P1 = 0, P2 - Pr = 0
    x = np.array([0.0, 0.0, a.supply_pressure, a.return_pressure])
    u, *_ = _law(x, ref=(0.05, 0.0, 0.0, 0.0))      # reference above: N > 0, "u ≥ 0" edge
    assert u == 0.0


def test_closed_loop_rests_at_equilibrium_with_zero_reference():
    a = Actuator()
    p = a.mass * a.gravity / (a.area_cap - a.area_rod)
    cfg = dataclasses.replace(Config(), reference=Reference(kind="zero"))
    cfg = dataclasses.replace(cfg, episode=dataclasses.replace(cfg.episode, horizon=2.0))
    tr = simulate(cfg, (150.0, 158.0, 162.0), x0=np.array([0.0, 0.0, p, p]))
    assert not tr.score.diverged
    assert np.max(np.abs(tr["y"])) < 1e-12
    assert np.max(np.abs(tr["u"])) < 1e-15


def test_lyapunov_function_decreases_at_the_designed_rate():
    """With â = a and adaptation off, V = ½(e1² + e2² + e3²) obeys V̇ = −Σ k_i e_i² ≤ −2·min(k)·V."""
    k = (150.0, 158.0, 162.0)
    a = dataclasses.replace(Actuator(), leakage=4e-12)              # true Ci = â2(0)
    cfg = Config(actuator=a, adaptation=Adaptation(gain=(0.0, 0.0)),
                 reference=Reference(kind="zero"))
    cfg = dataclasses.replace(cfg, episode=dataclasses.replace(cfg.episode, horizon=0.06))
    x0 = a.initial_state()
    x0[0] = 1e-3                                                    # start 1 mm off
    tr = simulate(cfg, k, x0=x0)
    v = 0.5 * (tr["e1"] ** 2 + tr["e2"] ** 2 + tr["e3"] ** 2)
    n = 150                                                         # 45 ms: V falls by 10^6
    assert np.all(np.diff(v[:n]) < 0.0)
    t = tr["t"][:n]
    bound = v[0] * np.exp(-2.0 * min(k) * t)
    assert np.all(v[:n] <= bound * 1.05)
    # and the decay is not much faster than the slowest designed mode allows
    assert v[n] > v[0] * np.exp(-2.0 * max(k) * t[-1] * 1.5)
