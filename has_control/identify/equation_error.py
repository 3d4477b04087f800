"""A start for the fit: the model's own equations, integrated over each
segment, solved by linear least squares (no differentiation of noisy data).

Force balance over [a, b]:  m·(ẏb − ẏa + g·T) + Bp·(yb − ya) = ∫(A1·P1 − A2·P2) dt,
linear in (m, Bp). Chambers, divided by βe:
    (1/βe)·Σ V1 ΔP1 = −A1·Δy − Ci·∫(P1 − P2) + G·∫xv·√Δp1,
    (1/βe)·Σ V2 ΔP2 =  A2·Δy + Ci·∫(P1 − P2) − G·∫xv·√Δp2,
linear in (1/βe, Ci, G), with the spool xv [m] the commands filtered by the
valve lag τ_v; τ_v is the grid value whose chamber fit leaves the smallest
residual. Segments at a pressure bound are left out (:mod:`.segments`).
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from has_control.identify.data import Experiment

#: Valve lags tried [s]: 0 (ideal) and 0.3 … 3 ms.
TAU_GRID = (0.0,) + tuple(np.round(np.arange(3e-4, 3.01e-3, 1.5e-4), 6))


def spool(u: np.ndarray, tau: float, dt: float, limit: float = 0.0) -> np.ndarray:
    """The spool position [m] at each sample: the (limited) commands through
    τ_v·ẋv = u − xv, from a centred spool, exact for a command held over each step."""
    c = np.clip(u, -limit, limit) if limit > 0.0 else np.asarray(u, dtype=np.float64)
    if tau <= 0.0:
        return c.copy()
    a = np.exp(-dt / tau)
    out = np.empty_like(c)
    out[0] = 0.0
    out[1:] = lfilter([1.0 - a], [1.0, -a], c[:-1])
    return out


def _sums(v, starts, length):
    """Σ over each segment's steps i = a .. b − 1 of the per-step values v."""
    cum = np.concatenate([[0.0], np.cumsum(v)])
    return cum[starts + length] - cum[starts]


def equation_error(exps: list[Experiment], starts: list[np.ndarray], length: int) -> dict[str, float]:
    """Estimates of mass, damping, bulk_modulus, leakage, valve_gain and
    valve_time_constant from the integrated equations (see the module)."""
    force_rows, force_rhs = [], []
    for exp, s in zip(exps, starts):
        a = exp.cfg.plant.actuator(exp.cfg.actuator)
        dt, x = exp.step, exp.x
        f = a.area_cap * x[:, 2] - a.area_rod * x[:, 3]
        fmid = 0.5 * (f[:-1] + f[1:]) * dt
        e = s + length
        force_rows.append(np.column_stack([x[e, 1] - x[s, 1] + a.gravity * length * dt, x[e, 0] - x[s, 0]]))
        force_rhs.append(_sums(fmid, s, length))
    (m, bp), *_ = np.linalg.lstsq(np.vstack(force_rows), np.concatenate(force_rhs), rcond=None)
    best = None
    for tau in TAU_GRID:
        theta, rms = _chambers(exps, starts, length, tau)
        if best is None or rms < best[2]:
            best = (tau, theta, rms)
    tau, (inv_beta, ci, g), _ = best
    return {"mass": float(m), "damping": float(bp), "bulk_modulus": float(1.0 / inv_beta) if inv_beta > 0 else np.nan,
            "leakage": float(ci), "valve_gain": float(g), "valve_time_constant": float(tau)}


def _chambers(exps, starts, length, tau):
    rows, rhs = [], []
    for exp, s in zip(exps, starts):
        a = exp.cfg.plant.actuator(exp.cfg.actuator)
        dt, x = exp.step, exp.x
        y, p1, p2 = x[:, 0], x[:, 2], x[:, 3]
        xv = spool(exp.u, tau, dt, exp.cfg.plant.valve_limit)
        ps, pr = a.supply_pressure, a.return_pressure
        pos = xv >= 0.0
        d1 = np.where(pos, ps - p1, p1 - pr).clip(min=0.0)
        d2 = np.where(pos, p2 - pr, ps - p2).clip(min=0.0)
        q1 = xv * np.sqrt(d1)
        q2 = xv * np.sqrt(d2)
        v1 = a.volume_cap0 + a.area_cap * y
        v2 = a.volume_rod0 - a.area_rod * y
        mid = lambda w: 0.5 * (w[:-1] + w[1:]) * dt  # noqa: E731
        dp = p1 - p2
        e = s + length
        dy = y[e] - y[s]
        vdp1 = _sums(0.5 * (v1[:-1] + v1[1:]) * np.diff(p1), s, length)
        vdp2 = _sums(0.5 * (v2[:-1] + v2[1:]) * np.diff(p2), s, length)
        idp = _sums(mid(dp), s, length)
        iq1 = _sums(mid(q1), s, length)
        iq2 = _sums(mid(q2), s, length)
        rows.append(np.column_stack([vdp1, idp, -iq1]))
        rhs.append(-a.area_cap * dy)
        rows.append(np.column_stack([vdp2, -idp, iq2]))
        rhs.append(a.area_rod * dy)
    A, b = np.vstack(rows), np.concatenate(rhs)
    col = np.abs(A).max(axis=0)
    col[col == 0] = 1.0
    theta, *_ = np.linalg.lstsq(A / col, b, rcond=None)
    theta = theta / col
    res = A @ theta - b
    return theta, float(np.sqrt(np.mean(res ** 2)))
