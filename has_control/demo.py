"""``scripts/demo``: tune the gains with PSO+CP+TVAC and compare with the paper (Table 3).

Tunes on the batch evaluator (reference configuration, one seed), runs the
manual and the tuned gains, prints manual vs tuned vs the paper's numbers,
and writes the figures.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .episode import simulate
from .params import MANUAL_GAINS, PAPER_TABLE3, PAPER_TUNED_GAINS, Config
from .tuning import load_tuning, tune

PAPER_ROWS = (("PSO+CP+TVAC-ABC (paper)", PAPER_TABLE3["tuned"]),
              ("ABC manual (paper)", PAPER_TABLE3["manual"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="scripts/demo", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/demo", help="directory for figures (default out/demo)")
    ap.add_argument("--seed", type=int, default=None)
    args = ap.parse_args(argv)
    from .cli import Progress
    from .plots import plot_convergence, plot_gains, plot_tracking

    cfg = Config()
    tuning = load_tuning()
    if args.seed is not None:
        tuning = tuning.replace(seed=args.seed)
    out = Path(args.out)
    print(f"Tuning k1, k2, k3 with {tuning.swarm.variant} (seed {tuning.seed}, "
          f"{tuning.swarm.particles} particles x {tuning.swarm.iterations} iterations, "
          f"10 s episodes at 0.3 ms) ...", flush=True)
    progress = Progress("  tuning")
    t0 = time.perf_counter()
    res = tune(cfg, tuning, callback=progress)
    progress.close()
    k = res.gains
    print(f"  best k = ({k[0]:.2f}, {k[1]:.2f}, {k[2]:.2f}), J = {res.result.fun:.6e}, "
          f"{res.result.nfev} episodes in {time.perf_counter() - t0:.1f} s")
    print("  paper (Table 2): k = (656.11, 656.13, 656.14), J = 7.8198e-4 (exponent sign lost in print)")
    print()
    print("Table 3, steady state 0.5 s .. 9.5 s, statistics of |e1|:")
    print(f"  {'controller':<30} {'k1':>8} {'k2':>8} {'k3':>8} {'J':>11} {'e_max [m]':>11} "
          f"{'e_mu [m]':>11} {'e_sigma [m]':>11}")
    traces = {}
    for label, g in (("ABC manual", MANUAL_GAINS.as_tuple()),
                     ("ABC, paper's tuned gains", PAPER_TUNED_GAINS.as_tuple()),
                     ("ABC, our PSO+CP+TVAC gains", k)):
        traces[label] = tr = simulate(cfg, g)
        s = tr.score
        print(f"  {label:<30} {g[0]:8.2f} {g[1]:8.2f} {g[2]:8.2f} {s.J:11.4e} {s.e_max:11.4e} "
              f"{s.e_mu:11.4e} {s.e_sigma:11.4e}")
    for label, (a, b, c) in PAPER_ROWS:
        print(f"  {label:<30} {'':8} {'':8} {'':8} {'':>11} {a:11.4e} {b:11.4e} {c:11.4e}")
    manual = traces["ABC manual"]
    tuned = traces["ABC, our PSO+CP+TVAC gains"]
    figs = [plot_tracking([("manual (150, 158, 162)", manual),
                           (f"tuned ({k[0]:.0f}, {k[1]:.0f}, {k[2]:.0f})", tuned)],
                          out / "tracking.png"),
            plot_convergence([(res.variant, res.result)], out / "convergence.png"),
            plot_gains(res.result, out / "gains.png", f"{res.variant}, seed {res.seed}")]
    print()
    print("Figures: " + ", ".join(str(f) for f in figs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
