"""``scripts/bench``: speed of the batch evaluator against baselines in the same process.

Prints figures only; never a pass/fail. Baselines: a NumPy implementation
vectorised over the same gain sets (has_control.baselines.run_numpy) and a
plain-Python loop (has_control.baselines.run), both on a shorter horizon and
compared per simulated sample.
"""
from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from . import baselines
from .episode import evaluate
from .params import Config

BOUNDS = (np.array([150.0, 150.0, 150.0]), np.array([1200.0, 800.0, 800.0]))


def _best_of(repeats: int, fn) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_evaluator(particles: int = 80, repeats: int = 3, numpy_horizon: float = 0.5,
                    python_horizon: float = 1.5) -> dict:
    cfg = Config()
    rng = np.random.default_rng(0)
    gains = rng.uniform(*BOUNDS, size=(particles, 3))
    n = cfg.episode.samples
    cores = numba.get_num_threads()
    evaluate(gains[:2])                                   # compile / load the cache
    t_batch = _best_of(repeats, lambda: evaluate(gains))
    per_sample_wall = t_batch / (particles * n)           # s per (sample × gain set), all cores
    n_np = round(numpy_horizon / cfg.episode.step)
    t_np = _best_of(1, lambda: baselines.run_numpy(gains, T=numpy_horizon))
    np_per = t_np / (particles * n_np)
    n_py = round(python_horizon / cfg.episode.step)
    t_py = _best_of(1, lambda: baselines.run((150.0, 158.0, 162.0), T=python_horizon))
    py_per = t_py / n_py
    return {
        "particles": particles, "samples": n, "cores": cores,
        "batch_seconds": t_batch,
        "ns_per_sample_per_core": per_sample_wall * cores * 1e9,
        "numpy_us_per_sample_per_gainset": np_per * 1e6,
        "python_us_per_sample": py_per * 1e6,
        "speedup_vs_numpy": np_per / per_sample_wall,
        "speedup_vs_python": py_per / per_sample_wall,
        "paper_experiment_seconds_estimate": 3 * 80 * 100 * n * per_sample_wall,
    }


def bench_graph(duration: float = 1.5) -> dict:
    """Lock-step samples per second through the ROS graph: one process, and two."""
    import os
    import re
    import subprocess
    import sys

    from .episode import with_horizon
    from .nodes.stack import run_stack
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=str(200 + os.getpid() % 30))
    cfg = with_horizon(Config(), duration)
    one = run_stack(cfg, domain_id=int(env["ROS_DOMAIN_ID"]))
    n = cfg.episode.samples
    cli = [sys.executable, "-m", "has_control.cli"]
    controller = subprocess.Popen(cli + ["controller"], env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
    try:
        plant = subprocess.run(cli + ["plant", "--ros-args", "-p", f"samples:={n}"], env=env,
                               capture_output=True, text=True, timeout=600)
    finally:
        controller.terminate()
        controller.wait(timeout=30)
    m = re.search(r"(\d+) samples/s", plant.stdout + plant.stderr)
    return {"samples": n, "one_process": len(one.trace) / one.seconds,
            "two_processes": float(m.group(1)) if m else float("nan")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/bench", description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    r = bench_evaluator(repeats=args.repeats)
    print(f"batch evaluator: {r['particles']} random gain sets x {r['samples']} samples "
          f"(10 s episodes) on {r['cores']} cores: {r['batch_seconds']:.3f} s "
          f"(best of {args.repeats})")
    print(f"  {r['ns_per_sample_per_core']:.1f} ns per sample per core")
    print(f"  NumPy baseline (vectorised over the 80 gain sets): "
          f"{r['numpy_us_per_sample_per_gainset']:.2f} us per sample per gain set "
          f"-> batch evaluator is {r['speedup_vs_numpy']:.0f}x faster (wall)")
    print(f"  plain-Python baseline (one gain set): {r['python_us_per_sample']:.1f} us per sample "
          f"-> batch evaluator is {r['speedup_vs_python']:.0f}x faster (wall)")
    print(f"  paper experiment (3 variants x 80 x 100 episodes), evaluator time: "
          f"{r['paper_experiment_seconds_estimate']:.1f} s")
    g = bench_graph()
    print(f"node graph, lock-step, {g['samples']} samples: {g['one_process']:,.0f} samples/s in one "
          f"process (EventsExecutor), {g['two_processes']:,.0f} samples/s across two processes "
          f"(real time at 0.3 ms is 3,333)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
