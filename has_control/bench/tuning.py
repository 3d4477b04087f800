"""The optimisers' cost outside the evaluator, the paper experiment run for real,
scenario evaluation against the number of scenarios, and a road scenario
against a sine one."""
from __future__ import annotations

import time

import numpy as np

from has_control.bench.timing import BOUNDS, _best_of
from has_control.config import CONFIG_DIR
from has_control.core.episode import evaluate, evaluate_configs, threads
from has_control.config import with_horizon
from has_control.core.params import Config, Reference
from has_control.core.reference import reference_array
from has_control.core.road import road_terms
from has_control.config import Scenario, load_scenarios, scenario_configs
from has_control.tuning.swarm import VARIANTS
from has_control.tuning.tuner import Tuning, tune


def bench_optimiser(iterations: int = 20, method: str = "pso-cp-tvac") -> dict:
    """Share of a tuning run spent in the optimiser itself (not in the evaluator):
    a swarm of ``iterations`` iterations, or cma-restarts with 80 x ``iterations`` evaluations."""
    cfg = Config()
    spent = [0.0]

    def objective(k):
        t0 = time.perf_counter()
        out = evaluate(k, cfg)
        spent[0] += time.perf_counter() - t0
        return out
    res = tune(cfg, Tuning().replace(variant=method, iterations=iterations, evaluations=80 * iterations),
               objective=objective, diagnostics=False)
    return {"method": method, "iterations": res.result.nit, "seconds": res.seconds,
            "optimiser_share": (res.seconds - spent[0]) / res.seconds}


def bench_paper(seed: int = 1) -> dict:
    """The paper experiment for one seed, run for real: three variants, 80
    particles, 100 iterations, one 10 s episode per candidate (24 000)."""
    cfg = Config()
    evaluate(np.array([[400.0, 400.0, 400.0]]), cfg)     # compile / load the cache
    runs = {}
    t0, c0 = time.perf_counter(), time.process_time()
    for variant in VARIANTS:
        res = tune(cfg, Tuning(seed=seed).replace(variant=variant))
        runs[variant] = {"seconds": res.seconds, "evaluations": res.result.nfev, "J": res.result.fun}
    return {"seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
            "episodes": sum(r["evaluations"] for r in runs.values()), "runs": runs, "cores": threads()}


def bench_scenarios(counts=(1, 10, 100), particles: int = 80, horizon: float = 2.0, repeats: int = 3) -> dict:
    """Episodes/s of ``particles`` candidates on 1, 10 and 100 scenarios
    (drifting plants as in config/scenarios.yaml), best of ``repeats``: the
    cost of scenario evaluation should be linear in their number."""
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


#: The references of :func:`bench_roads`: the sine of the reference
#: configuration, then roads at the shipped cutoff, near the most components
#: summed in the kernel, and past it (tabulated).
ROADS = {"sine": {}, "road, 2 Hz (shipped)": {"kind": "road"}, "road, 6 Hz": {"kind": "road", "cutoff": 6.0},
         "road, 50 Hz (tabulated)": {"kind": "road", "cutoff": 50.0}}


def bench_roads(particles: int = 80, repeats: int = 3) -> dict:
    """One 10 s scenario of each of :data:`ROADS`, ``particles`` candidates:
    wall time (a fresh road seed each time, so building the road counts)
    and the bytes of the reference array, best of ``repeats`` in alternating
    rounds."""
    gains = np.random.default_rng(0).uniform(*BOUNDS, size=(particles, 3))
    seeds = iter(range(1, 1_000_000))

    def config(kwargs):
        return Config(reference=Reference(**kwargs, seed=next(seeds)) if kwargs else Reference())
    for kwargs in ROADS.values():
        evaluate_configs(gains[:2], [config(kwargs)])                 # compile / load the cache
    best = dict.fromkeys(ROADS, float("inf"))
    for _ in range(repeats):
        for name, kwargs in ROADS.items():
            cfg = config(kwargs)
            t0 = time.perf_counter()
            evaluate_configs(gains, [cfg])
            best[name] = min(best[name], time.perf_counter() - t0)
    out = {}
    for name, kwargs in ROADS.items():
        cfg = config(kwargs)
        out[name] = {"seconds": best[name], "bytes": reference_array(cfg.reference, cfg.episode).nbytes,
                     "terms": road_terms(cfg.reference, cfg.episode) if kwargs else 0}
    return {"particles": particles, "horizon": Config().episode.horizon, "runs": out}
