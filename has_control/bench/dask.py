"""The batch evaluator on Dask against the local one, Dask's per-task costs, and the scaling model."""
from __future__ import annotations

import math
import time

import numpy as np

from has_control.bench.timing import BOUNDS, _best_of
from has_control.config import build_config
from has_control.core.episode import LANES, evaluate_configs
from has_control.core.params import Config
from has_control.tuning.dask_evaluator import dask_batch, modelled_seconds, plan_tasks


def _dask_scenarios(count: int, horizon: float) -> list:
    """``count`` Configs differing in the sine reference: amplitude 0.05-0.15 m,
    angular frequency 1-3 rad/s; ``horizon`` seconds each."""
    return [build_config({"simulation.horizon": horizon, "reference.amplitude": 0.05 + 0.1 * i / max(1, count - 1),
                          "reference.omega": 1.0 + 0.5 * (i % 5)}, source="bench --dask", base=Config())
            for i in range(count)]


def bench_dask(repeats: int = 3, particles: int = 80, scenarios: int = 20, horizon: float = 10.0,
               trivial_tasks: int = 400) -> dict:
    """``dask_batch("local:2")`` (2 worker processes x 1 thread) against
    ``evaluate_configs`` on 2 threads in this process, on ``particles`` x
    ``scenarios`` episodes of ``horizon`` seconds: alternating A/B, best of
    ``repeats``. Then what the scaling model needs: the kernel's time per
    block (LANES candidates, one episode, one thread), Dask's per-task costs
    (trivial tasks: wall per task, CPU of the client and scheduler in this
    process and of the workers; one task's round trip; and the same batch cut
    into one-block tasks, against the planned tasks)."""
    cfgs = _dask_scenarios(scenarios, horizon)
    gains = np.random.default_rng(0).uniform(*BOUNDS, size=(particles, 3))
    block = gains[:LANES]
    evaluate_configs(block, cfgs[:1], workers=1)                       # compile / load the cache
    t_block = _best_of(repeats, lambda: evaluate_configs(block, cfgs[:1], workers=1))
    t0 = time.perf_counter()
    with dask_batch("local:2") as batch:
        started = time.perf_counter() - t0
        nthreads = batch.client.nthreads()
        workers = len(nthreads)
        t1 = time.perf_counter()
        first = batch(gains, cfgs)                                      # sends the Configs
        first_call = time.perf_counter() - t1
        same = np.array_equal(first, evaluate_configs(gains, cfgs, workers=2))
        t_local = t_dask = float("inf")
        for _ in range(repeats):                                        # alternate A/B
            t_local = min(t_local, _best_of(1, lambda: evaluate_configs(gains, cfgs, workers=2)))
            t_dask = min(t_dask, _best_of(1, lambda: batch(gains, cfgs)))
        one = cfgs[:1]                                                  # a paper iteration: one scenario
        t_local_one = t_dask_one = float("inf")
        for _ in range(3 * repeats):
            t_local_one = min(t_local_one, _best_of(1, lambda: evaluate_configs(gains, one, workers=2)))
            t_dask_one = min(t_dask_one, _best_of(1, lambda: batch(gains, one)))
        planned = len(plan_tasks(particles, [c.episode.samples for c in cfgs], nthreads))
        batch.chunk = LANES                                             # one block a task
        t_fine = _best_of(1, lambda: batch(gains, cfgs))
        fine = len(plan_tasks(particles, [c.episode.samples for c in cfgs], nthreads, chunk=LANES))
        batch.chunk = None
        client = batch.client
        trivial = list(range(-trivial_tasks, 0))
        client.gather(client.map(abs, trivial, pure=False))
        t_trivial, cpu_here, cpu_workers = float("inf"), float("inf"), float("inf")
        for _ in range(repeats):
            w0, c0, k0 = time.perf_counter(), time.process_time(), sum(client.run(time.process_time).values())
            client.gather(client.map(abs, trivial, pure=False))
            w1, c1, k1 = time.perf_counter(), time.process_time(), sum(client.run(time.process_time).values())
            t_trivial, cpu_here = min(t_trivial, w1 - w0), min(cpu_here, c1 - c0)
            cpu_workers = min(cpu_workers, k1 - k0)
        latency = _best_of(10, lambda: client.submit(abs, -1, pure=False).result())
    episodes = particles * scenarios
    return {
        "particles": particles, "scenarios": scenarios, "horizon": horizon, "samples": cfgs[0].episode.samples,
        "workers": workers, "repeats": repeats, "same_bits": same, "start_seconds": started,
        "first_call_seconds": first_call, "local_seconds": t_local, "dask_seconds": t_dask,
        "local_episodes_per_second": episodes / t_local, "dask_episodes_per_second": episodes / t_dask,
        "ratio": t_dask / t_local, "one_scenario_local_seconds": t_local_one, "one_scenario_dask_seconds": t_dask_one,
        "planned_tasks": planned, "fine_tasks": fine, "fine_seconds": t_fine,
        "task_seconds_in_context": (t_fine - t_dask) * workers / (fine - planned),
        "block_seconds": t_block, "block_seconds_in_batch": t_local * 2 / (scenarios * math.ceil(particles / LANES)),
        "trivial_tasks": trivial_tasks, "trivial_seconds_per_task": t_trivial / trivial_tasks,
        "scheduler_cpu_per_task": cpu_here / trivial_tasks, "worker_cpu_per_task": cpu_workers / trivial_tasks,
        "round_trip_seconds": latency,
    }


#: (workers, threads per worker) of the scaling model: 8, 64 and 512 cores as
#: one-thread workers and as 8-thread workers (one per machine of 8 cores).
LAYOUTS = ((1, 1), (2, 1), (8, 1), (1, 8), (64, 1), (8, 8), (512, 1), (64, 8))


def dask_scaling(block_seconds: float, task_seconds: float, scheduler_task_seconds: float, round_trip: float,
                 particles: int = 80, iterations: int = 100) -> list[dict]:
    """The scaling model of docs/scaling.md: seconds per synchronous PSO
    iteration (``particles`` candidates under every scenario, then a barrier)
    on W workers of T threads, with the best chunking: round_trip + min over
    c of :func:`~has_control.tuning.dask_evaluator.modelled_seconds`, counted in units of T
    blocks (a worker's T threads run one unit in one block's time); and the
    ideal (the blocks spread evenly over the cores, no overhead)."""
    blocks = math.ceil(particles / LANES)
    rows = []
    for name, scenarios in (("paper", 1), ("robust", 100)):
        for workers, threads in LAYOUTS:
            units = math.ceil(blocks / threads)
            costs = {c: modelled_seconds(c, scenarios, units, workers, block_seconds, task_seconds,
                                         scheduler_task_seconds) for c in range(1, units + 1)}
            chunks = min(costs, key=costs.get)
            per_iteration = round_trip + costs[chunks]
            cores = workers * threads
            ideal = math.ceil(scenarios * blocks / cores) * block_seconds
            rows.append({"case": name, "scenarios": scenarios, "workers": workers, "threads": threads,
                         "cores": cores, "tasks": scenarios * chunks, "iteration_seconds": per_iteration,
                         "run_seconds": iterations * per_iteration, "ideal_iteration_seconds": ideal,
                         "speedup": scenarios * blocks * block_seconds / per_iteration,
                         "efficiency": ideal / per_iteration})
    return rows


def print_dask(r: dict) -> None:
    print(f"dask batch: {r['particles']} candidates x {r['scenarios']} scenarios, {r['horizon']:g} s episodes "
          f"({r['samples']} samples), best of {r['repeats']}, alternating A/B in this process")
    print(f"  local evaluate_configs, 2 threads: {r['local_seconds']:.3f} s, "
          f"{r['local_episodes_per_second']:.0f} episodes/s")
    print(f"  dask_batch('local:2'), {r['workers']} workers x 1 thread, {r['planned_tasks']} tasks: "
          f"{r['dask_seconds']:.3f} s, {r['dask_episodes_per_second']:.0f} episodes/s, "
          f"{'same' if r['same_bits'] else 'DIFFERENT'} bits")
    print(f"  ratio dask / local: {r['ratio']:.3f} (start-up and warm-up {r['start_seconds']:.1f} s, "
          f"first call with the Configs {r['first_call_seconds']:.3f} s, both outside the ratio)")
    print(f"  one scenario (a paper iteration, {r['particles']} episodes), best of {3 * r['repeats']}: local "
          f"{1e3 * r['one_scenario_local_seconds']:.1f} ms, dask {1e3 * r['one_scenario_dask_seconds']:.1f} ms, "
          f"ratio {r['one_scenario_dask_seconds'] / r['one_scenario_local_seconds']:.2f}")
    print(f"  kernel: one block ({8} candidates x one {r['horizon']:g} s episode, one thread) "
          f"{1e3 * r['block_seconds']:.2f} ms alone, {1e3 * r['block_seconds_in_batch']:.2f} ms in the local batch")
    print(f"  dask per task: {r['trivial_tasks']} trivial tasks {1e3 * r['trivial_seconds_per_task']:.2f} ms each "
          f"(wall); CPU {1e3 * r['scheduler_cpu_per_task']:.2f} ms in the client and scheduler, "
          f"{1e3 * r['worker_cpu_per_task']:.2f} ms in the workers; one task's round trip "
          f"{1e3 * r['round_trip_seconds']:.2f} ms")
    print(f"  dask per task in context: the batch as {r['fine_tasks']} one-block tasks takes "
          f"{r['fine_seconds']:.3f} s -> {1e3 * r['task_seconds_in_context']:.2f} ms per extra task per worker")
    rows = dask_scaling(r["block_seconds_in_batch"], r["worker_cpu_per_task"], r["scheduler_cpu_per_task"],
                        r["round_trip_seconds"])
    print(f"  scaling model (docs/scaling.md), 80 candidates, synchronous iterations; block "
          f"{1e3 * r['block_seconds_in_batch']:.2f} ms, task {1e3 * r['worker_cpu_per_task']:.2f} ms, "
          f"scheduler {1e3 * r['scheduler_cpu_per_task']:.2f} ms per task, "
          f"barrier {1e3 * r['round_trip_seconds']:.2f} ms:")
    print("    case      S  cores = W x T  tasks  ms/iteration  s/100 iterations  ideal ms/it  speed-up  efficiency")
    for w in rows:
        layout = f"{w['workers']} x {w['threads']}"
        print(f"    {w['case']:<6} {w['scenarios']:>4} {w['cores']:>6} = {layout:<7} {w['tasks']:>5} "
              f"{1e3 * w['iteration_seconds']:>13.1f} {w['run_seconds']:>17.2f} "
              f"{1e3 * w['ideal_iteration_seconds']:>12.1f} "
              f"{w['speedup']:>9.1f} {100 * w['efficiency']:>10.0f} %")
