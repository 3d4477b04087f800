"""The batch evaluator against baselines run in the same process.

Baselines: a plain numba loop of the same sample step, one candidate per
thread (timed alternately with the batch evaluator), a NumPy implementation
vectorised over the same gain sets (:func:`has_control.bench.baselines.run_numpy`)
and a plain-Python loop (:func:`has_control.bench.baselines.run`), the last two
on a shorter horizon and compared per simulated sample.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from has_control.bench import baselines
from has_control.bench.timing import BOUNDS, _best_of, _timed
from has_control.core.cost import metric_finish
from has_control.core.episode import EpisodeArrays, _constants, evaluate, sample_step, threads
from has_control.core.params import A1_INIT, A2_INIT, Config
from has_control.core.reference import reference


def _plain_kernel():
    """A straightforward numba loop over the same equations, for comparison:
    one candidate per thread (``prange``), the reference's sin/cos computed once
    per sample into a table, each sample one call of the core's
    :func:`~has_control.core.episode.sample_step`. Compiled here, not cached."""
    @njit(parallel=True, error_model="numpy", nogil=True)
    def plain(gains, ap, pp, cp, rp, sp, ep, x0, out):
        ap, pp, cp, sp, _, ep, dt, n, lo, hi, y_limit = _constants(ap, pp, cp, sp, ep)
        ref = np.empty((n, 4))
        for i in range(n):
            ref[i, 0], ref[i, 1], ref[i, 2], ref[i, 3] = reference(rp, i * dt)
        for p in prange(gains.shape[0]):
            x1, x2, x3, x4, xv = x0[0], x0[1], x0[2], x0[3], 0.0
            k1, k2, k3 = gains[p, 0], gains[p, 1], gains[p, 2]
            a1, a2 = cp[A1_INIT], cp[A2_INIT]
            x3d = j = count = mean = m2 = peak = 0.0
            out[p, 0] = out[p, 1] = out[p, 2] = out[p, 3] = math.inf
            for i in range(n):
                in_window = lo <= i <= hi
                if in_window:
                    count += 1.0
                x1, x2, x3, x4, xv, a1, a2, x3d, j, mean, m2, peak, bad, _, _, _, _ = sample_step(
                    x1, x2, x3, x4, xv, a1, a2, x3d, i > 0, ref[i, 0], ref[i, 1], ref[i, 2], ref[i, 3],
                    0.0, 0.0, 0.0, 0.0, False, k1, k2, k3, j, mean, m2, peak, count, in_window,
                    ap, pp, cp, ep, dt, y_limit)
                if bad:
                    break
            if not bad:
                out[p, 0] = j
                out[p, 1], out[p, 2], out[p, 3] = metric_finish(count, mean, m2, peak)
    return plain


def bench_evaluator(particles: int = 80, repeats: int = 3, numpy_horizon: float = 0.5,
                    python_horizon: float = 1.5) -> dict:
    """The batch evaluator (lane-vectorised blocks) against the plain loop of
    the same equations, alternating A/B in this process, best of ``repeats``;
    then the NumPy and plain-Python baselines on shorter horizons."""
    cfg = Config()
    rng = np.random.default_rng(0)
    gains = rng.uniform(*BOUNDS, size=(particles, 3))
    n = cfg.episode.samples
    cores = threads()
    arr = EpisodeArrays.from_config(cfg)
    plain = _plain_kernel()
    out = np.empty((particles, 4))

    def run_plain():
        plain(gains, arr.actuator, arr.plant, arr.adaptation, arr.reference, arr.sensor, arr.episode, arr.x0, out)
    evaluate(gains[:2])                                   # compile / load the cache
    run_plain()                                           # compile
    same = np.array_equal(out[:, 0], evaluate(gains))
    t_batch = t_plain = cpu_batch = cpu_plain = float("inf")
    for _ in range(repeats):                              # alternate A/B
        wall, cpu = _timed(lambda: evaluate(gains))
        t_batch, cpu_batch = min(t_batch, wall), min(cpu_batch, cpu)
        wall, cpu = _timed(run_plain)
        t_plain, cpu_plain = min(t_plain, wall), min(cpu_plain, cpu)
    per_sample_wall = t_batch / (particles * n)           # s per (sample × gain set), all cores
    n_np = round(numpy_horizon / cfg.episode.step)
    t_np = _best_of(1, lambda: baselines.run_numpy(gains, T=numpy_horizon))
    np_per = t_np / (particles * n_np)
    n_py = round(python_horizon / cfg.episode.step)
    t_py = _best_of(1, lambda: baselines.run((150.0, 158.0, 162.0), T=python_horizon))
    py_per = t_py / n_py
    return {
        "particles": particles, "samples": n, "cores": cores,
        "batch_seconds": t_batch, "plain_seconds": t_plain, "plain_same_bits": same,
        "ns_per_sample_per_core": per_sample_wall * cores * 1e9,
        "plain_ns_per_sample_per_core": t_plain / (particles * n) * cores * 1e9,
        "cpu_ns_per_sample": cpu_batch / (particles * n) * 1e9,
        "plain_cpu_ns_per_sample": cpu_plain / (particles * n) * 1e9,
        "ratio": t_batch / t_plain,
        "numpy_us_per_sample_per_gainset": np_per * 1e6,
        "python_us_per_sample": py_per * 1e6,
        "speedup_vs_numpy": np_per / per_sample_wall,
        "speedup_vs_python": py_per / per_sample_wall,
        "paper_experiment_seconds_estimate": 3 * 80 * 100 * n * per_sample_wall,
    }
