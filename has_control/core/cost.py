"""Tuning cost J and steady-state metrics (SPEC §6), sample by sample.

The same two accumulators serve the episode kernel (online, while simulating)
and :func:`score_series` (offline, over a recorded trace or bag), in the same
order of operations, so both give the same bits.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from has_control.core.jit import KERNEL, LEAF
from has_control.core.params import DT, LAMBDA1, LAMBDA2, LAMBDA3, WIN_END, WIN_START
from has_control.common.json_numbers import to_json


@njit(**LEAF)
def cost_increment(e1, u, ep):
    """(λ1|e1| + λ2·u² + λ3|e1|·[e1 < 0])·Δt for one sample."""
    ae = abs(e1)
    c = ep[LAMBDA1] * ae + ep[LAMBDA2] * u * u
    if e1 < 0.0:
        c += ep[LAMBDA3] * ae
    return c * ep[DT]


@njit(**LEAF)
def metric_update(count, mean, m2, peak, e1):
    """Welford update of count, mean and Σ(x − mean)² of |e1|, and its max."""
    x = abs(e1)
    count += 1.0
    d = x - mean
    mean += d / count
    m2 += d * (x - mean)
    return count, mean, m2, max(peak, x)


@njit(**LEAF)
def metric_finish(count, mean, m2, peak):
    """(e_max, e_μ, e_σ) with the population standard deviation."""
    if count == 0.0:
        return math.nan, math.nan, math.nan
    return peak, mean, math.sqrt(m2 / count)


@njit(**KERNEL)
def score_series(e1, u, ep):
    """(J, e_max, e_μ, e_σ) of recorded e1 [m] and u [m] on the grid of ``ep``.

    Sample i is in the metric window when WIN_START ≤ i ≤ WIN_END.
    """
    j = 0.0
    count = mean = m2 = peak = 0.0
    lo = int(ep[WIN_START])
    hi = int(ep[WIN_END])
    for i in range(e1.shape[0]):
        j += cost_increment(e1[i], u[i], ep)
        if lo <= i <= hi:
            count, mean, m2, peak = metric_update(count, mean, m2, peak, e1[i])
    e_max, e_mu, e_sigma = metric_finish(count, mean, m2, peak)
    return j, e_max, e_mu, e_sigma


@dataclass(frozen=True)
class Score:
    """Outcome of one episode: cost J [m·s + m²·s] and metrics of |e1| [m]."""

    J: float
    e_max: float
    e_mu: float
    e_sigma: float
    samples: int
    diverged: bool

    def as_json(self) -> dict:
        """The keys of ``has-control simulate --json``; inf as the string "inf"."""
        return {"J": to_json(self.J), "e_max": to_json(self.e_max), "e_mu": to_json(self.e_mu),
                "e_sigma": to_json(self.e_sigma), "samples": int(self.samples),
                "diverged": bool(self.diverged)}


def score_arrays(e1: np.ndarray, u: np.ndarray, ep_array: np.ndarray, diverged: bool = False) -> Score:
    """Score a recorded run (trace or bag). A diverged run scores +inf."""
    n = int(len(e1))
    if diverged:
        inf = math.inf
        return Score(inf, inf, inf, inf, n, True)
    j, a, b, c = score_series(np.ascontiguousarray(e1, dtype=np.float64),
                              np.ascontiguousarray(u, dtype=np.float64), ep_array)
    return Score(j, a, b, c, n, False)
