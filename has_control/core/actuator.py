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
    V_CAP0, V_ROD0, VALVE_GAIN, VALVE_LIMIT, VALVE_RATE,
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
    a1 = ap[AREA_CAP]
    a2 = ap[AREA_ROD]
    beta = ap[BULK]
    m = ap[MASS]
    v1, v2 = chamber_volumes(x1, ap)
    q1, q2 = valve_flows(x3, x4, u, ap)
    leak = ap[LEAKAGE] * (x3 - x4)
    dx2 = (a1 * x3 - a2 * x4 - m * ap[GRAVITY] - ap[DAMPING] * x2) / m
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
