"""``scripts/bench``: every benchmark of the project, one option each.

``scripts/bench --swarm`` (the optimisers against pyswarms, mealpy and SciPy in
a venv of their own) runs :mod:`has_control.bench.swarm_peers` through
``scripts/bench_swarm``; every other option runs here.

Prints figures only; never a pass/fail. Each figure is a ratio against a
baseline run in the same process, best of N (the machine is shared).
"""
from __future__ import annotations

import argparse

from has_control.bench.dask import bench_dask, print_dask
from has_control.bench.evaluator import bench_evaluator
from has_control.bench.foxglove import bench_foxglove
from has_control.bench.graph import bench_graph, print_graph
from has_control.bench.machines import bench_objectives, print_objectives
from has_control.bench.scoring import bench_scoring
from has_control.bench.tuning import bench_optimiser, bench_paper, bench_roads, bench_scenarios
from has_control.bench.startup import bench_startup, print_startup
from has_control.bench.tuners import print_tuners


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/bench", description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--paper", action="store_true",
                    help="run only the paper experiment for one seed, for real (12-20 s on 2 cores)")
    ap.add_argument("--evaluator", action="store_true",
                    help="run only the evaluator comparison (blocks against the plain loop)")
    ap.add_argument("--graph", action="store_true", help="run only the node-graph table (about a minute)")
    ap.add_argument("--startup", action="store_true",
                    help="run only the start-up row: a warm simulate --duration 2 against import numba, numpy")
    ap.add_argument("--scenarios", action="store_true",
                    help="run only the scenario scaling (episodes/s on 1, 10 and 100 scenarios) and a road "
                         "scenario's time and memory against a sine one's")
    ap.add_argument("--dask", action="store_true",
                    help="run only dask_batch('local:2') against the local batch, 80 x 20 episodes of 10 s, "
                         "Dask's per-task costs and the scaling model (about 30 s)")
    ap.add_argument("--foxglove", action="store_true",
                    help="run only the live view's cost per message (no client, one client, a list append)")
    ap.add_argument("--machines", action="store_true",
                    help="run only the objectives' cost per candidate (the paper's J, requirements, vouched, "
                         "robust) against today's robust tuning; the machine study is python -m "
                         "has_control.bench.machines")
    ap.add_argument("--tuners", action="store_true",
                    help="run only the tuning methods' study: cma-restarts, the paper's swarms, IPOP-CMA-ES, SciPy DE "
                         "over seeds at 8000/4000/2000 evaluations (CPU-heavy: about 70 s of CPU per seed)")
    ap.add_argument("--seeds", type=int, default=30, help="with --tuners: seeds 1..N (default 30)")
    ap.add_argument("--methods", nargs="+", metavar="NAME", help="with --tuners: only these methods")
    ap.add_argument("--budgets", nargs="+", type=int, metavar="N",
                    help="with --tuners: evaluations (default 8000 4000 2000)")
    ap.add_argument("--robust", action="store_true",
                    help="with --tuners: the robust objective (CVaR 0.2 over config/scenarios.yaml, 2 s episodes)")
    ap.add_argument("--markdown", metavar="FILE.md", help="with --tuners: also write the table there")
    args = ap.parse_args(argv)
    if args.foxglove:
        bench_foxglove()
        return 0
    if args.machines:
        print_objectives(bench_objectives(repeats=args.repeats))
        return 0
    if args.startup:
        print_startup(bench_startup(repeats=args.repeats), args.repeats)
        return 0
    if args.tuners:
        print_tuners(args.seeds, args.methods, args.budgets, args.robust, args.markdown)
        return 0
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
        r = bench_roads(repeats=args.repeats)
        sine = r["runs"]["sine"]
        print(f"one {r['horizon']:g} s scenario, {r['particles']} candidates, the road built in the time, "
              f"best of {args.repeats} alternating: time and reference memory against the sine")
        for name, run in r["runs"].items():
            terms = f", {run['terms']} components" if run["terms"] else ""
            print(f"  {name}{terms}: {run['seconds']:.3f} s ({run['seconds'] / sine['seconds']:.2f}x), "
                  f"{run['bytes']:,} bytes ({run['bytes'] / sine['bytes']:.1f}x)")
        return 0
    if args.graph:
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
    for method in ("pso-cp-tvac", "cma-restarts"):
        o = bench_optimiser(method=method)
        print(f"optimiser overhead: {100 * o['optimiser_share']:.2f} % of a {o['iterations']}-iteration "
              f"{o['method']} tuning run ({o['seconds']:.1f} s) is spent outside the evaluator")
    print(f"scoring a 10 s bag (33,333 samples, 5 topics): {bench_scoring():.3f} s")
    print_graph(bench_graph(repeats=args.repeats))
    print_startup(bench_startup(repeats=args.repeats), args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
