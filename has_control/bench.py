"""``scripts/bench``: speed of the batch evaluator against baselines in the same process.

Prints figures only; never a pass/fail. Baselines: a plain numba loop of the
same sample step, one candidate per thread (timed alternately with the batch
evaluator), a NumPy implementation vectorised over the same gain sets
(has_control.baselines.run_numpy) and a plain-Python loop
(has_control.baselines.run), the last two on a shorter horizon and compared per
simulated sample.
"""
from __future__ import annotations

import argparse
import math
import time

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


def _timed(fn) -> tuple[float, float]:
    """(wall, CPU) seconds of one call; CPU time sums every thread of the
    process, so it shows the work done even when another process shares a core."""
    w0, c0 = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0


def _plain_kernel():
    """A straightforward numba loop over the same equations, for comparison:
    one candidate per thread (``prange``), the reference's sin/cos computed once
    per sample into a table, each sample one call of the core's
    :func:`~has_control.episode.sample_step`. Compiled here, not cached."""
    import math

    from numba import njit, prange

    from .cost import metric_finish
    from .episode import _constants, sample_step
    from .params import A1_INIT, A2_INIT
    from .reference import reference

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
    from .episode import EpisodeArrays, threads
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


def bench_optimiser(iterations: int = 20) -> dict:
    """Share of a tuning run spent in the swarm itself (not in the evaluator)."""
    from .tuning import Tuning, tune
    cfg = Config()
    spent = [0.0]

    def objective(k):
        t0 = time.perf_counter()
        out = evaluate(k, cfg)
        spent[0] += time.perf_counter() - t0
        return out
    res = tune(cfg, Tuning().replace(iterations=iterations), objective=objective)
    return {"iterations": iterations, "seconds": res.seconds,
            "optimiser_share": (res.seconds - spent[0]) / res.seconds}


def bench_paper(seed: int = 1) -> dict:
    """The paper experiment for one seed, run for real: three variants, 80
    particles, 100 iterations, one 10 s episode per candidate (24 000)."""
    from .swarm import VARIANTS
    from .tuning import Tuning, tune
    cfg = Config()
    evaluate(np.array([[400.0, 400.0, 400.0]]), cfg)     # compile / load the cache
    runs = {}
    t0, c0 = time.perf_counter(), time.process_time()
    for variant in VARIANTS:
        res = tune(cfg, Tuning(seed=seed).replace(variant=variant))
        runs[variant] = {"seconds": res.seconds, "evaluations": res.result.nfev, "J": res.result.fun}
    from .episode import threads
    return {"seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
            "episodes": sum(r["evaluations"] for r in runs.values()), "runs": runs, "cores": threads()}


def bench_scenarios(counts=(1, 10, 100), particles: int = 80, horizon: float = 2.0, repeats: int = 3) -> dict:
    """Episodes/s of ``particles`` candidates on 1, 10 and 100 scenarios
    (drifting plants as in config/scenarios.yaml), best of ``repeats``: the
    cost of scenario evaluation should be linear in their number."""
    from .config import CONFIG_DIR
    from .episode import evaluate_configs, with_horizon
    from .scenarios import Scenario, load_scenarios, scenario_configs
    cfg = with_horizon(Config(), horizon)
    drawn = [s for s in load_scenarios(CONFIG_DIR / "scenarios_heldout.yaml") if s.name.startswith("held-out")]
    gains = np.random.default_rng(0).uniform(*BOUNDS, size=(particles, 3))
    evaluate_configs(gains[:2], scenario_configs(cfg, drawn[:2]))      # compile / load the cache
    out = {}
    for count in counts:
        sc = [Scenario(f"{drawn[i % len(drawn)].name}-{i}", drawn[i % len(drawn)].overrides) for i in range(count)]
        configs = scenario_configs(cfg, sc)
        t = _best_of(repeats, lambda: evaluate_configs(gains, configs))
        out[count] = {"seconds": t, "episodes_per_second": particles * count / t}
    return {"particles": particles, "horizon": horizon, "runs": out}


def _dask_scenarios(count: int, horizon: float) -> list:
    """``count`` Configs differing in the sine reference: amplitude 0.05-0.15 m,
    angular frequency 1-3 rad/s; ``horizon`` seconds each."""
    from .config import build_config
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
    from .cluster import dask_batch, plan_tasks
    from .episode import LANES, evaluate_configs
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
    c of :func:`~has_control.cluster.modelled_seconds`, counted in units of T
    blocks (a worker's T threads run one unit in one block's time); and the
    ideal (the blocks spread evenly over the cores, no overhead)."""
    from .cluster import modelled_seconds
    from .episode import LANES
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


def bench_scoring() -> float:
    """Seconds to score a 10 s bag (33 333 samples, 5 topics), best of 3."""
    import tempfile
    from pathlib import Path

    from .bag import PARAMETERS_KEY, BagWriter, parameters_json, score_bag, write_trace
    from .episode import simulate
    full = Config()
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "ten_seconds"
        with BagWriter(bag, {PARAMETERS_KEY: parameters_json(full)}) as w:
            write_trace(w, simulate(full), full)
        score_bag(bag)                                   # warm
        return _best_of(3, lambda: score_bag(bag))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/bench", description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--paper", action="store_true",
                    help="run only the paper experiment for one seed, for real (12-20 s on 2 cores)")
    ap.add_argument("--evaluator", action="store_true",
                    help="run only the evaluator comparison (blocks against the plain loop)")
    ap.add_argument("--graph", action="store_true", help="run only the node-graph table (about a minute)")
    ap.add_argument("--scenarios", action="store_true",
                    help="run only the scenario scaling: episodes/s on 1, 10 and 100 scenarios")
    ap.add_argument("--dask", action="store_true",
                    help="run only dask_batch('local:2') against the local batch, 80 x 20 episodes of 10 s, "
                         "Dask's per-task costs and the scaling model (about 30 s)")
    args = ap.parse_args(argv)
    if args.dask:
        print_dask(bench_dask(repeats=args.repeats))
        return 0
    if args.scenarios:
        r = bench_scenarios(repeats=args.repeats)
        base = r["runs"][1]["episodes_per_second"]
        print(f"scenario evaluation: {r['particles']} candidates x S scenarios, {r['horizon']:g} s episodes, "
              f"best of {args.repeats}")
        for count, run in r["runs"].items():
            print(f"  S = {count:3d}: {run['seconds']:.3f} s, {run['episodes_per_second']:,.0f} episodes/s "
                  f"({run['episodes_per_second'] / base:.2f}x the rate at S = 1)")
        return 0
    if args.graph:
        from .nodes.loopbench import bench_graph, print_graph
        print_graph(bench_graph(repeats=args.repeats))
        return 0
    if args.paper:
        r = bench_paper()
        print(f"paper experiment, seed 1, run for real: {r['episodes']:,} episodes of 10 s in "
              f"{r['seconds']:.1f} s wall on {r['cores']} cores (CPU time {r['cpu_seconds']:.1f} s)")
        for v, run in r["runs"].items():
            print(f"  {v}: {run['seconds']:.1f} s, {run['evaluations']:,} episodes, J = {run['J']:.6e}")
        return 0
    r = bench_evaluator(repeats=args.repeats)
    print(f"batch evaluator: {r['particles']} random gain sets x {r['samples']} samples "
          f"(10 s episodes) on {r['cores']} cores: {r['batch_seconds']:.3f} s "
          f"(best of {args.repeats}, alternating with the plain loop)")
    print(f"  lane-vectorised blocks: {r['ns_per_sample_per_core']:.1f} ns per sample per core "
          f"(CPU time {r['cpu_ns_per_sample']:.1f} ns per sample)")
    print(f"  plain loop (one candidate per thread, prange, same sample_step): "
          f"{r['plain_ns_per_sample_per_core']:.1f} ns per sample per core "
          f"(CPU time {r['plain_cpu_ns_per_sample']:.1f} ns), {r['plain_seconds']:.3f} s, "
          f"{'same' if r['plain_same_bits'] else 'DIFFERENT'} J bits")
    print(f"  ratio blocks / plain loop: {r['ratio']:.2f}")
    print(f"  NumPy baseline (vectorised over the 80 gain sets): "
          f"{r['numpy_us_per_sample_per_gainset']:.2f} us per sample per gain set "
          f"-> batch evaluator is {r['speedup_vs_numpy']:.0f}x faster (wall)")
    print(f"  plain-Python baseline (one gain set): {r['python_us_per_sample']:.1f} us per sample "
          f"-> batch evaluator is {r['speedup_vs_python']:.0f}x faster (wall)")
    print(f"  paper experiment (3 variants x 80 x 100 episodes), evaluator time: "
          f"{r['paper_experiment_seconds_estimate']:.1f} s")
    if args.evaluator:
        return 0
    o = bench_optimiser()
    print(f"optimiser overhead: {100 * o['optimiser_share']:.2f} % of a {o['iterations']}-iteration "
          f"tuning run ({o['seconds']:.1f} s) is spent outside the evaluator")
    print(f"scoring a 10 s bag (33,333 samples, 5 topics): {bench_scoring():.3f} s")
    from .nodes.loopbench import bench_graph, print_graph
    print_graph(bench_graph(repeats=args.repeats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
