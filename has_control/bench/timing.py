"""Timing helpers of the benchmarks: best-of-N wall time, wall and CPU time of one call."""
from __future__ import annotations

import time

import numpy as np

#: The tuning box of ``config/tuner.yaml`` [1/s], where the benchmarks draw random gain sets.
BOUNDS = (np.array([150.0, 150.0, 150.0]), np.array([1200.0, 800.0, 800.0]))


def _best_of(repeats: int, fn) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _timed(fn) -> tuple[float, float]:
    """(wall, CPU) seconds of one call; CPU time sums every thread of the
    process, so it shows the work done even when another process shares a core."""
    w0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0
