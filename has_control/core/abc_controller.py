"""The adaptive back-stepping control law (SPEC §3), one implementation.

Errors are desired minus actual. The unknown parameters a = (Bp, Ci) are
estimated by â with the discontinuous projection of paper Eq. 12. Functions
take flat arrays (:meth:`Actuator.as_array`, :meth:`Adaptation.as_array`) and
return tuples; the episode kernel and the controller node both call them.
"""
from __future__ import annotations

import math

from numba import njit

from has_control.core.jit import INLINE, LEAF
from has_control.core.actuator import chamber_volumes, valve_drops
from has_control.core.params import (
    A1_MAX, A1_MIN, A2_MAX, A2_MIN, AREA_CAP, AREA_ROD, BULK, GRAVITY, MASS, SIGMA1, SIGMA2, VALVE_GAIN,
    X3D_BACKWARD, X3D_MODE,
)


@njit(**LEAF)
def projection(a_hat, tau, lower, upper):
    """Proj(â, τ) (paper Eq. 12): 0 if â ≥ upper and τ > 0, 0 if â ≤ lower and τ < 0, else τ."""
    if a_hat >= upper and tau > 0.0:
        return 0.0
    if a_hat <= lower and tau < 0.0:
        return 0.0
    return tau


@njit(**INLINE)
def abc_law(x1, x2, p1, p2, a1_hat, a2_hat, x3d_prev, has_prev,
            r0, r1, r2, r3, k1, k2, k3, ap, cp, dt):
    """Valve command and internals at one sample.

    x1..p2: plant state (y [m], ẏ [m/s], P1 [Pa], P2 [Pa]); a1_hat, a2_hat:
    current estimates; x3d_prev, has_prev: x3d of the previous sample (used
    only by the backward-difference option); r0..r3: x1d and its derivatives;
    k1..k3: gains [1/s]; dt: sample time [s].

    Returns (u [m], e1 [m], e2 [m/s], e3 [N], rate1, rate2, x3d [N]) where
    rate_i = Proj(â_i, τ_i) is the projected adaptation rate.
    """
    m = ap[MASS]
    a1 = ap[AREA_CAP]
    a2 = ap[AREA_ROD]
    beta = ap[BULK]
    g = ap[GRAVITY]
    v1, v2 = chamber_volumes(x1, ap)
    force = a1 * p1 - a2 * p2

    e1 = r0 - x1
    x2d = r1 + k1 * e1
    e2 = x2d - x2
    de1 = r1 - x2
    dx2d = r2 + k1 * de1
    x3d = m * k2 * e2 + m * e1 + m * dx2d + a1_hat * x2 + m * g
    e3 = x3d - force

    gc = (a1 * a1 / v1 + a2 * a2 / v2) * beta * x2
    hu = (a1 / v1 + a2 / v2) * (p1 - p2) * beta
    rate1 = projection(a1_hat, cp[SIGMA1] * e2 * x2 / m, cp[A1_MIN], cp[A1_MAX])
    rate2 = projection(a2_hat, cp[SIGMA2] * hu * e3, cp[A2_MIN], cp[A2_MAX])

    if int(cp[X3D_MODE]) == X3D_BACKWARD:
        dx3d = (x3d - x3d_prev) / dt if has_prev else 0.0
    else:
        # computable part: ẋ2 replaced by v̂ = (F − m·g − â1·x2)/m
        v_hat = (force - m * g - a1_hat * x2) / m
        ddx2d = r3 + k1 * (r2 - v_hat)
        de2 = dx2d - v_hat
        dx3d = m * k2 * de2 + m * de1 + m * ddx2d + rate1 * x2 + a1_hat * v_hat

    num = k3 * e3 + gc + a2_hat * hu + dx3d + e2 / m
    d1, d2 = valve_drops(p1, p2, num >= 0.0, ap)      # the edges sign(N) opens
    b3 = (a1 * math.sqrt(d1) / v1 + a2 * math.sqrt(d2) / v2) * ap[VALVE_GAIN] * beta
    u = num / b3 if b3 > 0.0 else 0.0
    return u, e1, e2, e3, rate1, rate2, x3d


@njit(**INLINE)
def adapt(a1_hat, a2_hat, rate1, rate2, cp, dt):
    """SPEC §5 step 5: â ← clip(â + Δt·Proj(â, τ), a_min, a_max)."""
    n1 = min(max(a1_hat + dt * rate1, cp[A1_MIN]), cp[A1_MAX])
    n2 = min(max(a2_hat + dt * rate2, cp[A2_MIN]), cp[A2_MAX])
    return n1, n2
