"""Optimiser validation: our three swarm variants against pyswarms, mealpy and SciPy DE.

CEC-style protocol: shifted Sphere, Rosenbrock, Rastrigin, Ackley and Griewank
(the optimum moved to a fixed random point inside 80 % of the box), budget
10 000·D evaluations, error f(x) − f* at 1 %, 10 %, 50 % and 100 % of the
budget, one run per seed. Also our own problem, ``abc``: the cost J of the
ABC gains (k1, k2, k3) on the reference configuration, D = 3, at the paper's
budget of 80 × 100 = 8 000 evaluations; its "error" is J itself (f* unknown).
Three roles, one file:

  --run ours   (project venv: has_control.tuning.swarm)            -> JSON lines
  --run peers  (.venv-peers: pyswarms, mealpy, scipy)       -> JSON lines
  --serve      (project venv: J of gain rows read from stdin; the peers'
                venv has no numba, so ``abc`` is evaluated by this server)
  --report DIR (project venv: tables, Wilcoxon rank-sum p)  -> DIR/report.md

``--out FILE`` appends to FILE and skips the runs already in it, so a long
protocol can be run in pieces and resumed. ``scripts/bench --swarm`` runs all
roles. Peers are installed in their own venv (mealpy pins NumPy 1.x); they are
never dependencies of has_control.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

PARTICLES = 80
CHECKPOINTS = (0.01, 0.1, 0.5, 1.0)
SUCCESS = 1e-8
BOXES = {"sphere": 100.0, "rosenbrock": 30.0, "rastrigin": 5.12, "ackley": 32.0, "griewank": 600.0}
#: Our own problem: the paper's gain box and budget (SPEC §7 defaults).
ABC_LOWER, ABC_UPPER = (150.0, 150.0, 150.0), (1200.0, 800.0, 800.0)
ABC_BUDGET, ABC_VMAX = 80 * 100, 15.0


def _base(name: str, z: np.ndarray) -> np.ndarray:
    """Unshifted function of rows z (N, D); minimum 0 at z = 0 (Rosenbrock: z + 1)."""
    if name == "sphere":
        return np.sum(z * z, axis=1)
    if name == "rosenbrock":
        x = z + 1.0
        return np.sum(100.0 * (x[:, 1:] - x[:, :-1] ** 2) ** 2 + (x[:, :-1] - 1.0) ** 2, axis=1)
    if name == "rastrigin":
        return 10.0 * z.shape[1] + np.sum(z * z - 10.0 * np.cos(2 * np.pi * z), axis=1)
    if name == "ackley":
        d = z.shape[1]
        return (-20.0 * np.exp(-0.2 * np.sqrt(np.sum(z * z, axis=1) / d))
                - np.exp(np.sum(np.cos(2 * np.pi * z), axis=1) / d) + 20.0 + math.e)
    if name == "griewank":
        i = np.sqrt(np.arange(1, z.shape[1] + 1))
        return 1.0 + np.sum(z * z, axis=1) / 4000.0 - np.prod(np.cos(z / i), axis=1)
    raise ValueError(name)


class Problem:
    """A shifted test function that counts evaluations and keeps best-so-far at checkpoints."""

    def __init__(self, name: str, dim: int, cost=None):
        self.name, self.dim = name, dim
        if name == "abc":
            self.lower, self.upper = np.array(ABC_LOWER), np.array(ABC_UPPER)
            self.budget, self.cost = ABC_BUDGET, cost
        else:
            b = BOXES[name]
            self.lower, self.upper = np.full(dim, -b), np.full(dim, b)
            self.shift = np.random.default_rng(2024 + dim).uniform(-0.8 * b, 0.8 * b, dim)
            self.budget, self.cost = 10_000 * dim, lambda x: _base(name, x - self.shift)
        self.marks = [int(c * self.budget) for c in CHECKPOINTS]
        self.reset()

    def reset(self) -> None:
        self.count, self.best, self.at = 0, math.inf, {}
        self.reached = None

    def __call__(self, x) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        f = self.cost(x)
        for v in f:
            if self.count >= self.budget:
                break
            self.count += 1
            self.best = min(self.best, float(v))
            if self.reached is None and self.best < SUCCESS:
                self.reached = self.count
            if self.count in self.marks:
                self.at[self.count] = self.best
        return f

    def one(self, x) -> float:
        return float(self(x)[0])

    def errors(self) -> list[float]:
        return [self.at.get(m, self.best) for m in self.marks]


# --- runners ---------------------------------------------------------------------

def run_ours(variant: str, p: Problem, seed: int) -> None:
    # lazy: this file also runs in the peers' venv (scripts/bench --swarm), which has no has_control
    from has_control.tuning.methods import minimize
    # 20 % of the range on the test functions; SPEC's v_max on our own problem
    vmax = ABC_VMAX if p.name == "abc" else 0.2 * (p.upper[0] - p.lower[0])
    minimize(p, (p.lower, p.upper), method=variant, particles=PARTICLES,
             iterations=p.budget // PARTICLES, seed=seed, velocity_limit=vmax, target=0.0)


def run_pyswarms(p: Problem, seed: int) -> None:
    import pyswarms as ps
    np.random.seed(seed)
    opt = ps.single.GlobalBestPSO(n_particles=PARTICLES, dimensions=p.dim,
                                  options={"c1": 1.49445, "c2": 1.49445, "w": 0.729},
                                  bounds=(p.lower, p.upper), bh_strategy="nearest")
    opt.optimize(p, iters=p.budget // PARTICLES, verbose=False)


def run_mealpy(kind: str, p: Problem, seed: int) -> None:
    from mealpy import PSO, FloatVar
    cls = {"LDW_PSO": PSO.LDW_PSO, "HPSO_TVAC": PSO.HPSO_TVAC}[kind]
    model = cls(epoch=p.budget // PARTICLES - 1, pop_size=PARTICLES)
    problem = {"obj_func": p.one, "bounds": FloatVar(lb=p.lower.tolist(), ub=p.upper.tolist()),
               "minmax": "min", "log_to": None}
    model.solve(problem, seed=seed)


def run_de(p: Problem, seed: int) -> None:
    from scipy.optimize import differential_evolution
    popsize = max(1, PARTICLES // p.dim)
    maxiter = p.budget // (popsize * p.dim) - 1
    differential_evolution(lambda x: p.one(x), list(zip(p.lower, p.upper)), popsize=popsize,
                           maxiter=maxiter, tol=0.0, polish=False, seed=seed)


OURS = {"pso": lambda p, s: run_ours("pso", p, s), "pso-cp": lambda p, s: run_ours("pso-cp", p, s),
        "pso-cp-tvac": lambda p, s: run_ours("pso-cp-tvac", p, s)}
PEERS = {"pyswarms GlobalBestPSO": run_pyswarms,
         "mealpy LDW_PSO": lambda p, s: run_mealpy("LDW_PSO", p, s),
         "mealpy HPSO_TVAC": lambda p, s: run_mealpy("HPSO_TVAC", p, s),
         "scipy differential_evolution": run_de}


def abc_cost_local():
    """J of gain rows (N, 3) with the batch evaluator (project venv)."""
    # lazy: this file also runs in the peers' venv (scripts/bench --swarm), which has no has_control
    from has_control.core.episode import evaluate
    return evaluate


class AbcClient:
    """J of gain rows (N, 3) from a ``--serve`` process in the project venv."""

    def __init__(self, python: str):
        import subprocess
        self.proc = subprocess.Popen([python, __file__, "--serve"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE)

    def __call__(self, k: np.ndarray) -> np.ndarray:
        k = np.ascontiguousarray(k, dtype=np.float64)
        self.proc.stdin.write(np.int64(k.shape[0]).tobytes() + k.tobytes())
        self.proc.stdin.flush()
        return np.frombuffer(self.proc.stdout.read(8 * k.shape[0]), dtype=np.float64).copy()


def serve() -> int:
    """Read (int64 n, n×3 float64) requests from stdin; write n float64 costs J."""
    cost = abc_cost_local()
    cin, cout = sys.stdin.buffer, sys.stdout.buffer
    while len(head := cin.read(8)) == 8:
        n = int(np.frombuffer(head, dtype=np.int64)[0])
        k = np.frombuffer(cin.read(24 * n), dtype=np.float64).reshape(n, 3)
        cout.write(np.asarray(cost(k), dtype=np.float64).tobytes())
        cout.flush()
    return 0


def _key(r: dict) -> tuple:
    """What makes one run: optimiser, function, dimension and seed."""
    return r["optimiser"], r["function"], r["dim"], r["seed"]


def _read_runs(*paths: Path) -> list[dict]:
    """Runs in JSON-lines files (missing files: none), first of each key kept."""
    unique = {}
    for path in paths:
        if path.exists():
            for line in path.read_text().splitlines():
                if line.strip():
                    r = json.loads(line)
                    unique.setdefault(_key(r), r)   # pieces run in parallel may repeat a run
    return list(unique.values())


def run(group: dict, dims, seeds: int, functions, out: Path | None, abc_python: str | None) -> None:
    done = {_key(r) for r in _read_runs(out)} if out else set()
    sink = out.open("a") if out else sys.stdout
    cases = [(fn, 3) for fn in functions if fn == "abc"] + [
        (fn, d) for d in dims for fn in functions if fn != "abc"]
    for fn, dim in cases:
        cost = None
        if fn == "abc":
            cost = AbcClient(abc_python) if abc_python else abc_cost_local()
        p = Problem(fn, dim, cost)
        for name, runner in group.items():
            for seed in range(1, seeds + 1):
                if (name, fn, dim, seed) in done:
                    continue
                p.reset()
                t0 = time.perf_counter()
                runner(p, seed)
                sink.write(json.dumps({"optimiser": name, "function": fn, "dim": dim, "seed": seed,
                                       "errors": p.errors(), "reached": p.reached, "evaluations": p.count,
                                       "seconds": time.perf_counter() - t0}) + "\n")
                sink.flush()


# --- report ----------------------------------------------------------------------

def report(directory: Path) -> Path:
    from scipy.stats import ranksums
    rows = _read_runs(directory / "ours.jsonl", directory / "peers.jsonl")
    names = list(dict.fromkeys(r["optimiser"] for r in rows))
    ours = [n for n in names if n in OURS]
    peers = [n for n in names if n not in OURS]
    out = [f"# Swarm validation (budget 10 000·D, {PARTICLES} particles / population)", "",
           "Error f(x) − f* of the best found; n: runs (seeds 1..n); success: error < 1e-8 (evaluations "
           "to reach it: mean over successful runs). p: Wilcoxon rank-sum of final errors, each of our "
           "variants vs the peer; '<' ours lower (better) median, '>' the peer's.", ""]
    cases = [("abc", 3)] + [(fn, d) for d in sorted({r["dim"] for r in rows}) for fn in BOXES]
    cases = [c for c in cases if any(r["function"] == c[0] and r["dim"] == c[1] for r in rows)]
    out += ["## Summary: median final error (runs)", "",
            "| optimiser | " + " | ".join("ABC J" if fn == "abc" else f"{fn}-{d}" for fn, d in cases) + " |",
            "|---" * (len(cases) + 1) + "|"]
    for n in names:
        cells = []
        for fn, dim in cases:
            e = [r["errors"][-1] for r in rows
                 if r["optimiser"] == n and r["function"] == fn and r["dim"] == dim]
            cells.append(f"{np.median(e):{'.5g' if fn == 'abc' else '.3g'}} ({len(e)})" if e else "–")
        out.append(f"| {n} | " + " | ".join(cells) + " |")
    out.append("")
    for fn, dim in cases:
        sel = [r for r in rows if r["dim"] == dim and r["function"] == fn]
        if not sel:
            continue
        title = (f"## Our problem: J of the ABC gains, D = 3, {ABC_BUDGET:,} evaluations "
                 "(the paper's budget; 'error' is J itself)" if fn == "abc" else f"## {fn}, D = {dim}")
        out += [title, "",
                "| optimiser | n | mean | median | std | best | err@1% | err@10% | err@50% | success "
                "| evals to 1e-8 |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        final = {}
        for n in names:
            rs = [r for r in sel if r["optimiser"] == n]
            if not rs:
                continue
            e = np.array([r["errors"][-1] for r in rs])
            final[n] = e
            ok = [r["reached"] for r in rs if r["reached"] is not None]
            mid = [np.median([r["errors"][i] for r in rs]) for i in range(3)]
            fmt = ".5g" if fn == "abc" else ".3g"
            succ = f"{len(ok)}/{len(rs)} | {np.mean(ok):,.0f}" if ok else f"0/{len(rs)} | –"
            out.append(f"| {n} | {len(rs)} | " + " | ".join(
                format(v, fmt) for v in (e.mean(), np.median(e), e.std(), e.min(), *mid))
                + f" | {succ} |")
        out += ["", "| ours vs peer | " + " | ".join(peers) + " |", "|---" * (len(peers) + 1) + "|"]
        for o in ours:
            cells = []
            for q in peers:
                if o in final and q in final:
                    pv = ranksums(final[o], final[q]).pvalue
                    side = "<" if np.median(final[o]) < np.median(final[q]) else (
                        ">" if np.median(final[o]) > np.median(final[q]) else "=")
                    cells.append(f"{side} p = {pv:.2g}")
                else:
                    cells.append("–")
            out.append(f"| {o} | " + " | ".join(cells) + " |")
        out.append("")
    path = directory / "report.md"
    path.write_text("\n".join(out) + "\n")
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", choices=("ours", "peers"))
    ap.add_argument("--report", metavar="DIR")
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--dims", type=int, nargs="+", default=[10, 30])
    ap.add_argument("--functions", nargs="+", default=list(BOXES) + ["abc"],
                    choices=list(BOXES) + ["abc"])
    ap.add_argument("--optimisers", nargs="+", metavar="NAME",
                    help="a subset of the group's optimisers (names as in the report)")
    ap.add_argument("--out", metavar="FILE", help="append JSON lines here, skipping runs already in it")
    ap.add_argument("--abc-python", metavar="PYTHON",
                    help="project venv's python, to serve J for 'abc' to the peers' venv")
    ap.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.serve:
        return serve()
    if args.report:
        print(report(Path(args.report)))
    elif args.run:
        group = OURS if args.run == "ours" else PEERS
        if args.optimisers:
            unknown = [n for n in args.optimisers if n not in group]
            if unknown:
                ap.error(f"--optimisers: unknown {unknown[0]!r}; {args.run}: {', '.join(group)}")
            group = {n: group[n] for n in args.optimisers}
        run(group, args.dims, args.seeds, args.functions,
            Path(args.out) if args.out else None, args.abc_python)
    return 0


if __name__ == "__main__":
    sys.exit(main())
