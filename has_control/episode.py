"""One closed-loop episode (SPEC §5), as a trace or as a parallel batch of costs.

Both entry points run the same compiled loop, :func:`_episode`, which calls
the one implementation of the reference, the control law, the cost and the
plant step. ``simulate`` records the time series; ``evaluate`` scores many
gain sets in parallel over all cores, deterministically.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numba
from numba import njit, prange

from .abc_controller import abc_law, adapt
from .actuator import diverged, plant_step
from .cost import Score, cost_increment, metric_finish, metric_update
from .jit import KERNEL
from .params import (
    A1_INIT, A2_INIT, DT, N_SAMPLES, WIN_END, WIN_START, Y_LIMIT, Config, Gains,
)
from .reference import reference

#: Columns of a trace, in order. Units: s, m, m, m/s, Pa, Pa, m, m, m/s, N, N·s/m, m³/(s·Pa).
TRACE_COLUMNS = ("t", "x1d", "y", "ydot", "P1", "P2", "u", "e1", "e2", "e3", "a1_hat", "a2_hat")
_NCOL = len(TRACE_COLUMNS)



#: Most candidates advanced together in one block of the batch kernel.
#: Independent candidates interleave in the CPU's pipelines (the RK4 chain of
#: sqrt and division is latency-bound for one candidate alone).
MAX_LANES = 16


@njit(**KERNEL)
def _episode(k1, k2, k3, ap, cp, rp, ep, x0, trace):
    """Run one episode; fill ``trace`` rows if it has any. Returns
    (J, e_max, e_μ, e_σ, samples, diverged)."""
    dt = ep[DT]
    n = int(ep[N_SAMPLES])
    lo = int(ep[WIN_START])
    hi = int(ep[WIN_END])
    y_limit = ep[Y_LIMIT]
    record = trace.shape[0] > 0
    x1 = x0[0]
    x2 = x0[1]
    x3 = x0[2]
    x4 = x0[3]
    a1_hat = cp[A1_INIT]
    a2_hat = cp[A2_INIT]
    x3d_prev = 0.0
    j = 0.0
    count = mean = m2 = peak = 0.0
    for i in range(n):
        t = i * dt
        r0, r1, r2, r3 = reference(rp, t)
        u, e1, e2, e3, rate1, rate2, x3d = abc_law(
            x1, x2, x3, x4, a1_hat, a2_hat, x3d_prev, i > 0, r0, r1, r2, r3, k1, k2, k3, ap, cp, dt)
        j += cost_increment(e1, u, ep)
        if lo <= i <= hi:
            count, mean, m2, peak = metric_update(count, mean, m2, peak, e1)
        if record:
            row = trace[i]
            row[0] = t
            row[1] = r0
            row[2] = x1
            row[3] = x2
            row[4] = x3
            row[5] = x4
            row[6] = u
            row[7] = e1
            row[8] = e2
            row[9] = e3
            row[10] = a1_hat
            row[11] = a2_hat
        a1_hat, a2_hat = adapt(a1_hat, a2_hat, rate1, rate2, cp, dt)
        x3d_prev = x3d
        x1, x2, x3, x4 = plant_step(x1, x2, x3, x4, u, ap, dt)
        if diverged(x1, x2, x3, x4, y_limit) or not math.isfinite(u):
            return math.inf, math.inf, math.inf, math.inf, i + 1, True
    e_max, e_mu, e_sigma = metric_finish(count, mean, m2, peak)
    return j, e_max, e_mu, e_sigma, n, False


# rows of a block's lane state
_X1, _X2, _X3, _X4, _A1, _A2, _X3D, _J, _MEAN, _M2, _PEAK, _DEAD = range(12)


@njit(**KERNEL)
def _block(gains, first, last, ap, cp, rp, ep, x0, out):
    """Episodes of candidates first..last-1 advanced sample by sample together.

    Per lane, the arithmetic is exactly :func:`_episode`'s, so a candidate's
    score does not depend on which block or lane it ran in.
    """
    lanes = last - first
    dt = ep[DT]
    n = int(ep[N_SAMPLES])
    lo = int(ep[WIN_START])
    hi = int(ep[WIN_END])
    y_limit = ep[Y_LIMIT]
    s = np.zeros((12, lanes))
    for q in range(lanes):
        s[_X1, q] = x0[0]
        s[_X2, q] = x0[1]
        s[_X3, q] = x0[2]
        s[_X4, q] = x0[3]
        s[_A1, q] = cp[A1_INIT]
        s[_A2, q] = cp[A2_INIT]
    count = 0.0
    alive = lanes
    for i in range(n):
        r0, r1, r2, r3 = reference(rp, i * dt)
        in_window = lo <= i <= hi
        if in_window:
            count += 1.0
        for q in range(lanes):
            if s[_DEAD, q] > 0.0:
                continue
            p = first + q
            x1 = s[_X1, q]
            x2 = s[_X2, q]
            x3 = s[_X3, q]
            x4 = s[_X4, q]
            a1_hat = s[_A1, q]
            a2_hat = s[_A2, q]
            u, e1, e2, e3, rate1, rate2, x3d = abc_law(
                x1, x2, x3, x4, a1_hat, a2_hat, s[_X3D, q], i > 0, r0, r1, r2, r3,
                gains[p, 0], gains[p, 1], gains[p, 2], ap, cp, dt)
            s[_J, q] += cost_increment(e1, u, ep)
            if in_window:
                # the block counts window samples once, for all lanes
                _, s[_MEAN, q], s[_M2, q], s[_PEAK, q] = metric_update(
                    count - 1.0, s[_MEAN, q], s[_M2, q], s[_PEAK, q], e1)
            s[_A1, q], s[_A2, q] = adapt(a1_hat, a2_hat, rate1, rate2, cp, dt)
            s[_X3D, q] = x3d
            y, v, p1, p2 = plant_step(x1, x2, x3, x4, u, ap, dt)
            s[_X1, q] = y
            s[_X2, q] = v
            s[_X3, q] = p1
            s[_X4, q] = p2
            if diverged(y, v, p1, p2, y_limit) or not math.isfinite(u):
                s[_DEAD, q] = i + 1.0
                alive -= 1
        if alive == 0:
            break
    for q in range(lanes):
        p = first + q
        if s[_DEAD, q] > 0.0:
            out[p, 0] = out[p, 1] = out[p, 2] = out[p, 3] = math.inf
            out[p, 4] = s[_DEAD, q]
            out[p, 5] = 1.0
        else:
            e_max, e_mu, e_sigma = metric_finish(count, s[_MEAN, q], s[_M2, q], s[_PEAK, q])
            out[p, 0] = s[_J, q]
            out[p, 1] = e_max
            out[p, 2] = e_mu
            out[p, 3] = e_sigma
            out[p, 4] = n
            out[p, 5] = 0.0


@njit(**KERNEL, parallel=True)
def _batch(gains, edges, ap, cp, rp, ep, x0, out):
    for b in prange(edges.shape[0] - 1):
        _block(gains, edges[b], edges[b + 1], ap, cp, rp, ep, x0, out)


def _block_edges(count: int) -> np.ndarray:
    """Split ``count`` candidates into blocks of at most MAX_LANES, a multiple
    of the thread count so every core gets the same share."""
    threads = max(1, numba.get_num_threads())
    blocks = threads * max(1, math.ceil(count / (threads * MAX_LANES)))
    blocks = max(1, min(blocks, count))
    return np.linspace(0, count, blocks + 1).round().astype(np.int64)


@dataclass(frozen=True)
class EpisodeArrays:
    """The flat arrays the kernel reads, built once from a :class:`Config`."""

    actuator: np.ndarray
    adaptation: np.ndarray
    reference: np.ndarray
    episode: np.ndarray
    x0: np.ndarray

    @classmethod
    def from_config(cls, cfg: Config) -> "EpisodeArrays":
        return cls(cfg.actuator.as_array(), cfg.adaptation.as_array(), cfg.reference.as_array(),
                   cfg.episode.as_array(), cfg.actuator.initial_state())


@dataclass(frozen=True)
class Trace:
    """Time series of one episode (rows = samples, columns = TRACE_COLUMNS) and its score."""

    data: np.ndarray
    score: Score
    gains: Gains

    def __getitem__(self, column: str) -> np.ndarray:
        return self.data[:, TRACE_COLUMNS.index(column)]


def with_horizon(cfg: Config, duration: float | None) -> Config:
    """``cfg`` with its episode horizon set to ``duration`` seconds (None: unchanged)."""
    if duration is None:
        return cfg
    from .config import build_config
    return build_config({"simulation.horizon": float(duration)}, source="--duration", base=cfg)


def simulate(cfg: Config | None = None, gains: Gains | tuple | None = None,
             x0: np.ndarray | None = None) -> Trace:
    """Run one episode and return its :class:`Trace`.

    ``gains`` defaults to ``cfg.gains``; ``x0`` (y, ẏ, P1, P2) to SPEC §4's
    initial state. A diverged run's trace stops at the sample that diverged.
    """
    cfg = cfg or Config()
    g = _as_gains(gains if gains is not None else cfg.gains)
    arr = EpisodeArrays.from_config(cfg)
    start = arr.x0 if x0 is None else np.asarray(x0, dtype=np.float64)
    trace = np.zeros((cfg.episode.samples, _NCOL))
    j, a, b, c, n, bad = _episode(g.k1, g.k2, g.k3, arr.actuator, arr.adaptation, arr.reference,
                                  arr.episode, start, trace)
    return Trace(trace[:n], Score(j, a, b, c, int(n), bool(bad)), g)


def evaluate(gains, cfg: Config | None = None, metrics: bool = False) -> np.ndarray:
    """Score many gain sets in parallel.

    gains: (P, 3) array of (k1, k2, k3). Returns the (P,) costs J, or with
    ``metrics`` a (P, 4) array of (J, e_max, e_μ, e_σ). Diverged runs give +inf.
    Deterministic: each row depends on its gains only.
    """
    cfg = cfg or Config()
    k = np.ascontiguousarray(np.atleast_2d(np.asarray(gains, dtype=np.float64)))
    if k.ndim != 2 or k.shape[1] != 3:
        raise ValueError(f"gains: expected shape (P, 3), got {np.shape(gains)}")
    arr = EpisodeArrays.from_config(cfg)
    out = np.empty((k.shape[0], 6))
    _batch(k, _block_edges(k.shape[0]), arr.actuator, arr.adaptation, arr.reference, arr.episode, arr.x0, out)
    return out[:, :4].copy() if metrics else out[:, 0].copy()


def _as_gains(g) -> Gains:
    if isinstance(g, Gains):
        return g
    k1, k2, k3 = (float(v) for v in g)
    return Gains(k1, k2, k3)


__all__ = ["TRACE_COLUMNS", "EpisodeArrays", "Trace", "simulate", "evaluate", "with_horizon"]
