"""Actuator physics (SPEC §2): the 4-state model and its RK4 step.

State x = (y [m], ẏ [m/s], P1 [Pa], P2 [Pa]); valve command u is the spool
displacement [m]. Functions take the flat parameter array of
:meth:`has_control.core.params.Actuator.as_array` (or the plant array of
:meth:`~has_control.core.params.Plant.as_array`, which begins with it and adds
the valve's travel limit and lag) and return tuples, so the hot
loop allocates nothing. They are the only implementation of the plant: the
episode kernel, the plant node and the tests all call them.
"""
from __future__ import annotations

import math

from numba import njit

from has_control.core.jit import INLINE, LEAF
from has_control.core.params import (
    AREA_CAP, AREA_ROD, BULK, DAMPING, GRAVITY, LEAKAGE, MASS, P_RETURN, P_SUPPLY,
    V_CAP0, V_ROD0, VALVE_GAIN, VALVE_LIMIT, VALVE_RATE, VALVE_OMEGA, VALVE_ZETA, SUBSTEPS, FRICTION_COULOMB,
    FRICTION_STRIBECK, STRIBECK_VELOCITY, FRICTION_SMOOTHING, STRUCTURE, STRUCTURE_FULL, STRUCTURE_REFERENCE,
)


@njit(**LEAF)
def valve_flows(p1, p2, u, ap):
    """Servo-valve flows (q1 into the cap chamber, q2 out of the rod chamber) [m³/s].

    q1 = G·u·[s(u)√(Ps − P1) + s(−u)√(P1 − Pr)],
    q2 = G·u·[s(u)√(P2 − Pr) + s(−u)√(Ps − P2)], roots floored at 0.
    """
    d1, d2 = valve_drops(p1, p2, u >= 0.0, ap)
    gu = ap[VALVE_GAIN] * u
    return gu * math.sqrt(d1), gu * math.sqrt(d2)


@njit(**LEAF)
def valve_drops(p1, p2, opening, ap):
    """Pressure drops [Pa] across the two metering edges, floored at 0.

    opening (u ≥ 0): (Ps − P1, P2 − Pr); otherwise (P1 − Pr, Ps − P2).
    """
    ps = ap[P_SUPPLY]
    pr = ap[P_RETURN]
    if opening:
        return max(ps - p1, 0.0), max(p2 - pr, 0.0)
    return max(p1 - pr, 0.0), max(ps - p2, 0.0)


@njit(**LEAF)
def chamber_volumes(y, ap):
    """(V1, V2) [m³] at displacement y [m]: V01 + A1·y and V02 − A2·y."""
    return ap[V_CAP0] + ap[AREA_CAP] * y, ap[V_ROD0] - ap[AREA_ROD] * y


@njit(**INLINE)
def joint_state(y, v, p1, p2, ap):
    """The state in the bond-graph reading of sensor_msgs/JointState (see
    :mod:`has_control.wire.topics`): position (y [m], V1, V2 [m³]), velocity
    (ẏ [m/s], V̇1 = A1·ẏ, V̇2 = −A2·ẏ [m³/s]), effort (F = A1·P1 − A2·P2 [N],
    P1, P2 [Pa]), as nine values in that order. Scalars or arrays."""
    v1, v2 = chamber_volumes(y, ap)
    a1 = ap[AREA_CAP]
    a2 = ap[AREA_ROD]
    return y, v1, v2, v, a1 * v, -a2 * v, a1 * p1 - a2 * p2, p1, p2


@njit(**INLINE)
def derivative(x1, x2, x3, x4, u, ap):
    """ẋ of the actuator (SPEC §2) at state (x1..x4) with the spool at u [m]."""
    return derivative_with_friction(x1, x2, x3, x4, u, ap, 0.0)


@njit(**LEAF)
def friction_force(v, pp):
    """Coulomb + Stribeck friction [N] on the piston at velocity v [m/s], against
    the motion (plant array ``pp``): F = (Fc + (Fs − Fc)·e^(−(v/v_s)²))·v/√(v² + ε²),
    the sign smoothed over ε = friction_smoothing [m/s] so RK4 sees a smooth
    right-hand side (|v| ≫ ε: the sign; v = 0: 0). The viscous part is ``damping``."""
    fc = pp[FRICTION_COULOMB]
    r = v / pp[STRIBECK_VELOCITY]
    eps = pp[FRICTION_SMOOTHING]
    return (fc + (pp[FRICTION_STRIBECK] - fc) * math.exp(-r * r)) * v / math.sqrt(v * v + eps * eps)


@njit(**INLINE)
def derivative_with_friction(x1, x2, x3, x4, u, ap, friction):
    """:func:`derivative` with a friction force [N] against the piston in the
    force balance: m·ẍ = A1·P1 − A2·P2 − m·g − B·ẋ − friction (friction = 0:
    :func:`derivative`'s bits, x − 0 being x)."""
    a1 = ap[AREA_CAP]
    a2 = ap[AREA_ROD]
    beta = ap[BULK]
    m = ap[MASS]
    v1, v2 = chamber_volumes(x1, ap)
    q1, q2 = valve_flows(x3, x4, u, ap)
    leak = ap[LEAKAGE] * (x3 - x4)
    dx2 = (a1 * x3 - a2 * x4 - m * ap[GRAVITY] - ap[DAMPING] * x2 - friction) / m
    dx3 = beta * (-a1 * x2 - leak + q1) / v1
    dx4 = beta * (a2 * x2 + leak - q2) / v2
    return x2, dx2, dx3, dx4


@njit(**INLINE)
def rk4_valve_step(x1, x2, x3, x4, xv, u, ap, dt, rate):
    """One classical Runge-Kutta step of length dt [s] with the valve command
    u [m] held (zero-order hold), for a valve whose spool xv [m] lags the
    command, τ_v·ẋv = u − xv with rate = 1/τ_v [1/s]: xv is a fifth state of
    the same step, and the flows of every stage see that stage's spool.
    rate = 0 is the ideal valve: the spool is u at every stage (xv unused),
    which is the 4-state step of SPEC §5 exactly. Returns (x1..x4, xv)."""
    lag = rate > 0.0
    h2 = 0.5 * dt
    s1 = xv if lag else u
    a1, a2, a3, a4 = derivative(x1, x2, x3, x4, s1, ap)
    av = (u - s1) * rate
    s2 = xv + h2 * av if lag else u
    b1, b2, b3, b4 = derivative(x1 + h2 * a1, x2 + h2 * a2, x3 + h2 * a3, x4 + h2 * a4, s2, ap)
    bv = (u - s2) * rate
    s3 = xv + h2 * bv if lag else u
    c1, c2, c3, c4 = derivative(x1 + h2 * b1, x2 + h2 * b2, x3 + h2 * b3, x4 + h2 * b4, s3, ap)
    cv = (u - s3) * rate
    s4 = xv + dt * cv if lag else u
    d1, d2, d3, d4 = derivative(x1 + dt * c1, x2 + dt * c2, x3 + dt * c3, x4 + dt * c4, s4, ap)
    dv = (u - s4) * rate
    s = dt / 6.0
    return (x1 + s * (a1 + 2.0 * b1 + 2.0 * c1 + d1),
            x2 + s * (a2 + 2.0 * b2 + 2.0 * c2 + d2),
            x3 + s * (a3 + 2.0 * b3 + 2.0 * c3 + d3),
            x4 + s * (a4 + 2.0 * b4 + 2.0 * c4 + d4),
            xv + s * (av + 2.0 * bv + 2.0 * cv + dv) if lag else u)


@njit(**INLINE)
def rk4_step(x1, x2, x3, x4, u, ap, dt):
    """One classical Runge-Kutta step of length dt [s] with u held (zero-order hold), ideal valve."""
    y, v, p1, p2, _ = rk4_valve_step(x1, x2, x3, x4, u, u, ap, dt, 0.0)
    return y, v, p1, p2


@njit(**INLINE)
def valve_plant_step(x1, x2, x3, x4, xv, u, pp, dt):
    """One step of the plant of plant array ``pp`` (:meth:`Plant.as_array`):
    the command u [m] limited to ±pp[VALVE_LIMIT] (0: no limit), the RK4 step
    with the valve of rate pp[VALVE_RATE], then P1, P2 clipped into [Pr, Ps].
    With an unlimited ideal valve it is :func:`plant_step` exactly. Returns (x1..x4, xv)."""
    limit = pp[VALVE_LIMIT]
    applied = min(max(u, -limit), limit) if limit > 0.0 else u
    y, v, p1, p2, spool = rk4_valve_step(x1, x2, x3, x4, xv, applied, pp, dt, pp[VALVE_RATE])
    p1, p2 = clip_pressures(p1, p2, pp)
    return y, v, p1, p2, spool


@njit(**LEAF)
def _spool_rates(s, w, u, rate, k, c, second):
    """(ẋv, ẇv) of the spool at position s [m], velocity w [m/s] with command u [m]:
    second order ẍv = k(u − xv) − c·ẋv (k = ω_n², c = 2ζω_n), else the first-order lag (u − xv)·rate."""
    return (w, k * (u - s) - c * w) if second else ((u - s) * rate, 0.0)


@njit(**INLINE)
def rk4_spool_step(x1, x2, x3, x4, xv, wv, u, pp, dt):
    """One RK4 step of length dt [s] of the actuator and its spool (xv [m],
    ẋv [m/s]) with u [m] held, under plant array ``pp``: the valve is ideal
    (xv = u), a first-order lag (pp[VALVE_RATE] > 0, as
    :func:`rk4_valve_step`, the same bits) or a second-order spool
    (pp[VALVE_OMEGA] > 0): then with a travel limit the flows of each stage see
    the stage's spool clipped to ±limit, and the step's spool is held at the
    stop, its velocity zeroed. Friction (:func:`friction_force`) acts when
    pp[STRUCTURE] is STRUCTURE_FULL. Returns (x1..x4, xv, ẋv)."""
    rate = pp[VALVE_RATE]
    om = pp[VALVE_OMEGA]
    limit = pp[VALVE_LIMIT]
    second = om > 0.0
    moving = second | (rate > 0.0)
    stop = second & (limit > 0.0)
    k = om * om
    c = 2.0 * pp[VALVE_ZETA] * om
    fric = pp[STRUCTURE] == STRUCTURE_FULL
    h2 = 0.5 * dt
    s1 = xv if moving else u
    w1 = wv
    f1 = friction_force(x2, pp) if fric else 0.0
    a1, a2, a3, a4 = derivative_with_friction(x1, x2, x3, x4, min(max(s1, -limit), limit) if stop else s1, pp, f1)
    av, aw = _spool_rates(s1, w1, u, rate, k, c, second)
    s2 = xv + h2 * av if moving else u
    w2 = wv + h2 * aw
    y2 = x2 + h2 * a2
    f2 = friction_force(y2, pp) if fric else 0.0
    b1, b2, b3, b4 = derivative_with_friction(x1 + h2 * a1, y2, x3 + h2 * a3, x4 + h2 * a4,
                                              min(max(s2, -limit), limit) if stop else s2, pp, f2)
    bv, bw = _spool_rates(s2, w2, u, rate, k, c, second)
    s3 = xv + h2 * bv if moving else u
    w3 = wv + h2 * bw
    y3 = x2 + h2 * b2
    f3 = friction_force(y3, pp) if fric else 0.0
    c1, c2, c3, c4 = derivative_with_friction(x1 + h2 * b1, y3, x3 + h2 * b3, x4 + h2 * b4,
                                              min(max(s3, -limit), limit) if stop else s3, pp, f3)
    cv, cw = _spool_rates(s3, w3, u, rate, k, c, second)
    s4 = xv + dt * cv if moving else u
    w4 = wv + dt * cw
    y4 = x2 + dt * c2
    f4 = friction_force(y4, pp) if fric else 0.0
    d1, d2, d3, d4 = derivative_with_friction(x1 + dt * c1, y4, x3 + dt * c3, x4 + dt * c4,
                                              min(max(s4, -limit), limit) if stop else s4, pp, f4)
    dv, dw = _spool_rates(s4, w4, u, rate, k, c, second)
    s = dt / 6.0
    xn = xv + s * (av + 2.0 * bv + 2.0 * cv + dv) if moving else u
    wn = wv + s * (aw + 2.0 * bw + 2.0 * cw + dw) if second else 0.0
    held = stop & (abs(xn) > limit)
    return (x1 + s * (a1 + 2.0 * b1 + 2.0 * c1 + d1),
            x2 + s * (a2 + 2.0 * b2 + 2.0 * c2 + d2),
            x3 + s * (a3 + 2.0 * b3 + 2.0 * c3 + d3),
            x4 + s * (a4 + 2.0 * b4 + 2.0 * c4 + d4),
            min(max(xn, -limit), limit) if held else xn,
            0.0 if held else wn)


@njit(**INLINE)
def spool_plant_step(x1, x2, x3, x4, xv, wv, u, pp, dt):
    """One sample of any plant (plant array ``pp``): the command u [m] (already
    delayed) limited to ±pp[VALVE_LIMIT], then pp[SUBSTEPS] RK4 steps of
    dt/substeps (:func:`rk4_spool_step`, u held), P1, P2 clipped into
    [Pr, Ps] after each. Substeps are taken only when pp[STRUCTURE] is
    STRUCTURE_FULL (else one step). Returns (x1..x4, xv, ẋv)."""
    limit = pp[VALVE_LIMIT]
    applied = min(max(u, -limit), limit) if limit > 0.0 else u
    if pp[STRUCTURE] == STRUCTURE_FULL:
        n = int(pp[SUBSTEPS])
        h = dt / n
        for _ in range(n):
            x1, x2, x3, x4, xv, wv = rk4_spool_step(x1, x2, x3, x4, xv, wv, applied, pp, h)
            x3, x4 = clip_pressures(x3, x4, pp)
        return x1, x2, x3, x4, xv, wv
    x1, x2, x3, x4, xv, wv = rk4_spool_step(x1, x2, x3, x4, xv, wv, applied, pp, dt)
    x3, x4 = clip_pressures(x3, x4, pp)
    return x1, x2, x3, x4, xv, wv


@njit(**INLINE)
def any_plant_step(x1, x2, x3, x4, xv, wv, u, pp, dt):
    """:func:`valve_plant_step` for a reference-structure plant (its bits), else
    :func:`spool_plant_step`. Returns (x1..x4, xv, ẋv)."""
    if pp[STRUCTURE] == STRUCTURE_REFERENCE:
        y, v, p1, p2, sv = valve_plant_step(x1, x2, x3, x4, xv, u, pp, dt)
        return y, v, p1, p2, sv, 0.0
    return spool_plant_step(x1, x2, x3, x4, xv, wv, u, pp, dt)


@njit(**INLINE)
def plant_step(x1, x2, x3, x4, u, ap, dt):
    """SPEC §5 step 6: RK4 step, then P1, P2 clipped into [Pr, Ps]."""
    y, v, p1, p2 = rk4_step(x1, x2, x3, x4, u, ap, dt)
    p1, p2 = clip_pressures(p1, p2, ap)
    return y, v, p1, p2


@njit(**LEAF)
def clip_pressures(p1, p2, ap):
    """P1, P2 [Pa] clipped into [Pr, Ps]."""
    lo = ap[P_RETURN]
    hi = ap[P_SUPPLY]
    return min(max(p1, lo), hi), min(max(p2, lo), hi)


@njit(**LEAF)
def diverged(x1, x2, x3, x4, y_limit):
    """SPEC §5 step 7: a state that is not finite or |y| > y_limit [m].

    Written with ``&`` and ``|`` (no short-circuit), so a loop over lanes that
    calls it has no branch."""
    finite = math.isfinite(x1) & math.isfinite(x2) & math.isfinite(x3) & math.isfinite(x4)
    return (not finite) | (abs(x1) > y_limit)
