"""Independent, slow implementations of SPEC.md §1–6 for checks and benchmarks.

``run`` is a plain-Python transcription written from SPEC.md alone, sharing
no code with the compiled core, so the core's reference numbers are checked
by a second implementation before they are pinned (test_episode.py). It is
also the plain-Python baseline of ``scripts/bench``. ``run_numpy`` is what a
user pairing a swarm library with NumPy would write: the same loop,
vectorised over gain sets. Both are fixed to the reference configuration.
"""
import math

import numpy as np

P = dict(m=1500.0, A1=5.67e-3, A2=1.256e-3, be=7.0e8, Bp=2600.0, Ci=3.0e-13, V01=1.0e-3,
         V02=1.0e-3, g=9.8, Ps=1.78e7, Pr=0.0, G=3.78e-4)
ADAPT = dict(s1=95000.0, s2=1e-49, a0=(2600.0, 4e-12), amin=(2600.0, 4e-12), amax=(3000.0, 1e-11))


def f(x, u):
    y, v, p1, p2 = x
    V1 = P["V01"] + P["A1"] * y
    V2 = P["V02"] - P["A2"] * y
    if u >= 0:
        q1 = P["G"] * u * math.sqrt(max(P["Ps"] - p1, 0.0))
        q2 = P["G"] * u * math.sqrt(max(p2 - P["Pr"], 0.0))
    else:
        q1 = P["G"] * u * math.sqrt(max(p1 - P["Pr"], 0.0))
        q2 = P["G"] * u * math.sqrt(max(P["Ps"] - p2, 0.0))
    return [
        v,
        (P["A1"] * p1 - P["A2"] * p2 - P["m"] * P["g"] - P["Bp"] * v) / P["m"],
        P["be"] / V1 * (-P["A1"] * v - P["Ci"] * (p1 - p2) + q1),
        P["be"] / V2 * (P["A2"] * v + P["Ci"] * (p1 - p2) - q2),
    ]


def rk4(x, u, h):
    k1 = f(x, u)
    k2 = f([a + h / 2 * b for a, b in zip(x, k1)], u)
    k3 = f([a + h / 2 * b for a, b in zip(x, k2)], u)
    k4 = f([a + h * b for a, b in zip(x, k3)], u)
    return [a + h / 6 * (b + 2 * c + 2 * d + e) for a, b, c, d, e in zip(x, k1, k2, k3, k4)]


def proj(a, tau, lo, hi):
    if a >= hi and tau > 0:
        return 0.0
    if a <= lo and tau < 0:
        return 0.0
    return tau


def control(x, ahat, t, k):
    y, v, p1, p2 = x
    m, A1, A2, be = P["m"], P["A1"], P["A2"], P["be"]
    k1, k2, k3 = k
    xd = 0.11 * math.sin(2 * t)
    xd1 = 0.22 * math.cos(2 * t)
    xd2 = -0.44 * math.sin(2 * t)
    xd3 = -0.88 * math.cos(2 * t)
    V1 = P["V01"] + A1 * y
    V2 = P["V02"] - A2 * y
    F = A1 * p1 - A2 * p2
    e1 = xd - y
    x2d = xd1 + k1 * e1
    e2 = x2d - v
    e1dot = xd1 - v
    x2d_dot = xd2 + k1 * e1dot
    x3d = m * k2 * e2 + m * e1 + m * x2d_dot + ahat[0] * v + m * P["g"]
    e3 = x3d - F
    gc = (A1 ** 2 / V1 + A2 ** 2 / V2) * be * v
    hu = (A1 / V1 + A2 / V2) * (p1 - p2) * be
    vhat = (F - m * P["g"] - ahat[0] * v) / m
    x2d_ddot = xd3 + k1 * (xd2 - vhat)
    e2dot = x2d_dot - vhat
    r1 = proj(ahat[0], ADAPT["s1"] * e2 * v / m, ADAPT["amin"][0], ADAPT["amax"][0])
    r2 = proj(ahat[1], ADAPT["s2"] * hu * e3, ADAPT["amin"][1], ADAPT["amax"][1])
    x3d_dot = m * k2 * e2dot + m * e1dot + m * x2d_ddot + r1 * v + ahat[0] * vhat
    N = k3 * e3 + gc + ahat[1] * hu + x3d_dot + e2 / m
    if N >= 0:
        E1, E2 = math.sqrt(max(P["Ps"] - p1, 0)), math.sqrt(max(p2 - P["Pr"], 0))
    else:
        E1, E2 = math.sqrt(max(p1 - P["Pr"], 0)), math.sqrt(max(P["Ps"] - p2, 0))
    b3 = (A1 * E1 / V1 + A2 * E2 / V2) * P["G"] * be
    u = N / b3 if b3 != 0 else 0.0
    return u, e1, (r1, r2)


def run(k, T=10.0, dt=3e-4):
    """(J, e_max, e_mu, e_sigma, samples, diverged) per SPEC §5–6."""
    n = round(T / dt)
    p2 = P["Ps"] / 2
    x = [0.0, 0.0, (P["m"] * P["g"] + P["A2"] * p2) / P["A1"], p2]
    ahat = list(ADAPT["a0"])
    J = 0.0
    window = []
    i0 = math.ceil(0.5 / dt - 1e-9)
    i1 = math.floor((T - 0.5) / dt + 1e-9)
    for i in range(n):
        t = i * dt
        u, e1, rates = control(x, ahat, t, k)
        J += (0.001 * abs(e1) + 0.999 * u * u + (10 * abs(e1) if e1 < 0 else 0.0)) * dt
        if i0 <= i <= i1:
            window.append(abs(e1))
        ahat = [min(max(a + dt * r, lo), hi) for a, r, lo, hi in
                zip(ahat, rates, ADAPT["amin"], ADAPT["amax"])]
        x = rk4(x, u, dt)
        x[2] = min(max(x[2], P["Pr"]), P["Ps"])
        x[3] = min(max(x[3], P["Pr"]), P["Ps"])
        if not all(math.isfinite(s) for s in x) or abs(x[0]) > 1:
            return math.inf, math.inf, math.inf, math.inf, i + 1, True
    mu = sum(window) / len(window)
    sigma = math.sqrt(sum((w - mu) ** 2 for w in window) / len(window))
    return J, max(window), mu, sigma, n, False


def run_numpy(gains, T=10.0, dt=3e-4):
    """Costs J of many gain sets, (P, 3) → (P,), vectorised over gain sets with NumPy.

    Diverged runs give inf. Same scheme as :func:`run`, without the metrics.
    """
    k = np.asarray(gains, dtype=float)
    k1, k2, k3 = k[:, 0], k[:, 1], k[:, 2]
    npart = len(k)
    m, A1, A2, be, G = P["m"], P["A1"], P["A2"], P["be"], P["G"]
    Ps, Pr = P["Ps"], P["Pr"]
    p2 = Ps / 2
    x = np.empty((4, npart))
    x[:] = np.array([0.0, 0.0, (m * P["g"] + A2 * p2) / A1, p2])[:, None]
    a1h = np.full(npart, ADAPT["a0"][0])
    a2h = np.full(npart, ADAPT["a0"][1])
    J = np.zeros(npart)
    dead = np.zeros(npart, dtype=bool)

    def f(x, u):
        y, v, p1, p2 = x
        V1 = P["V01"] + A1 * y
        V2 = P["V02"] - A2 * y
        pos = u >= 0
        q1 = G * u * np.sqrt(np.maximum(np.where(pos, Ps - p1, p1 - Pr), 0.0))
        q2 = G * u * np.sqrt(np.maximum(np.where(pos, p2 - Pr, Ps - p2), 0.0))
        leak = P["Ci"] * (p1 - p2)
        return np.stack([v, (A1 * p1 - A2 * p2 - m * P["g"] - P["Bp"] * v) / m,
                         be / V1 * (-A1 * v - leak + q1), be / V2 * (A2 * v + leak - q2)])

    with np.errstate(all="ignore"):
        for i in range(round(T / dt)):
            t = i * dt
            xd, xd1 = 0.11 * math.sin(2 * t), 0.22 * math.cos(2 * t)
            xd2, xd3 = -0.44 * math.sin(2 * t), -0.88 * math.cos(2 * t)
            y, v, p1, p2 = x
            V1 = P["V01"] + A1 * y
            V2 = P["V02"] - A2 * y
            F = A1 * p1 - A2 * p2
            e1 = xd - y
            e2 = xd1 + k1 * e1 - v
            e1dot = xd1 - v
            x2d_dot = xd2 + k1 * e1dot
            e3 = m * k2 * e2 + m * e1 + m * x2d_dot + a1h * v + m * P["g"] - F
            gc = (A1 ** 2 / V1 + A2 ** 2 / V2) * be * v
            hu = (A1 / V1 + A2 / V2) * (p1 - p2) * be
            vhat = (F - m * P["g"] - a1h * v) / m
            tau1 = ADAPT["s1"] * e2 * v / m
            tau2 = ADAPT["s2"] * hu * e3
            amax, amin = ADAPT["amax"], ADAPT["amin"]
            r1 = np.where(((a1h >= amax[0]) & (tau1 > 0)) | ((a1h <= amin[0]) & (tau1 < 0)), 0.0, tau1)
            r2 = np.where(((a2h >= amax[1]) & (tau2 > 0)) | ((a2h <= amin[1]) & (tau2 < 0)), 0.0, tau2)
            x3d_dot = (m * k2 * (x2d_dot - vhat) + m * e1dot + m * (xd3 + k1 * (xd2 - vhat))
                       + r1 * v + a1h * vhat)
            N = k3 * e3 + gc + a2h * hu + x3d_dot + e2 / m
            pos = N >= 0
            E1 = np.sqrt(np.maximum(np.where(pos, Ps - p1, p1 - Pr), 0.0))
            E2 = np.sqrt(np.maximum(np.where(pos, p2 - Pr, Ps - p2), 0.0))
            b3 = (A1 * E1 / V1 + A2 * E2 / V2) * G * be
            u = np.where(b3 != 0, N / np.where(b3 != 0, b3, 1.0), 0.0)
            J += (0.001 * np.abs(e1) + 0.999 * u * u + np.where(e1 < 0, 10 * np.abs(e1), 0.0)) * dt
            a1h = np.clip(a1h + dt * r1, ADAPT["amin"][0], ADAPT["amax"][0])
            a2h = np.clip(a2h + dt * r2, ADAPT["amin"][1], ADAPT["amax"][1])
            s1 = f(x, u)
            s2 = f(x + dt / 2 * s1, u)
            s3 = f(x + dt / 2 * s2, u)
            s4 = f(x + dt * s3, u)
            x = x + dt / 6 * (s1 + 2 * s2 + 2 * s3 + s4)
            x[2:] = np.clip(x[2:], Pr, Ps)
            dead |= ~np.all(np.isfinite(x), axis=0) | (np.abs(x[0]) > 1)
    return np.where(dead, np.inf, J)
