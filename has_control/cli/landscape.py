"""``has-control landscape``: the tuning objective J over 2-D slices of the gain
space through a point, as heatmaps with the box's bound and the local minima
marked (nominal, or robust with --scenarios/--aggregate)."""
from __future__ import annotations

import argparse
import json

from has_control.cli.args import (add_config, add_duration, add_json, batch, check_outputs, dask_spec, figure_path,
                                  gains_arg, load, number)
from has_control.core.params import PAPER_TUNED_GAINS
from has_control.tuning.landscape import NAMES, check_plan, slices
from has_control.tuning.tuner import load_tuning, make_objective, robust_tuning

MAX_POINTS = 300                 # a side of a slice's grid; points² x scenarios is bounded by check_plan


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--point", nargs=3, metavar=("K1", "K2", "K3"),
                   help="the slices pass through these gains [1/s] (default: the paper's tuned 656.11 656.13 656.14)")
    p.add_argument("--points", type=number(3, MAX_POINTS, int), default=40, metavar="N",
                   help="grid points per side (default 40)")
    p.add_argument("--beyond", type=number(0.0, 10.0), default=0.25, metavar="F",
                   help="extend each slice past the upper bound by F x the range (default 0.25)")
    add_config(p, "ros__parameters YAML (episode, swarm.lower/upper: the box; repeatable)")
    add_duration(p)
    p.add_argument("--scenarios", metavar="FILE", help="robust objective: every scenario of this YAML file")
    p.add_argument("--aggregate", metavar="HOW", help="with --scenarios: mean (default), max or cvar:ALPHA")
    p.add_argument("--dask", type=dask_spec, metavar="SPEC", help="evaluate on a Dask cluster (see tune)")
    p.add_argument("--plot", type=figure_path, metavar="FILE.png", help="write the heatmaps")
    add_json(p, "print one JSON object (the grids too)")


def run(args) -> int:
    check_outputs(args, files=("plot",))
    cfg = load(args)
    tuning = robust_tuning(load_tuning(args.config or []), cfg, args.scenarios, args.aggregate)
    episodes = check_plan(args.points, len(tuning.scenarios))
    point = gains_arg(args.point, "--point") if args.point else PAPER_TUNED_GAINS.as_tuple()
    with batch(args) as evaluator:
        grid = slices(make_objective(cfg, tuning, evaluator), point, tuning.lower, tuning.upper,
                      points=args.points, beyond=args.beyond, scenarios=len(tuning.scenarios))
    objective = (f"{tuning.aggregate} of J over {len(tuning.scenarios)} scenarios" if tuning.scenarios
                 else "J, nominal model")
    if args.plot:
        from has_control.plots.landscape import plot_landscape       # lazy: matplotlib takes a second to load
        plot_landscape(grid, args.plot, f"{objective}, {cfg.episode.horizon:g} s episodes, through "
                                        f"k = ({point[0]:g}, {point[1]:g}, {point[2]:g})")
    if args.json:
        print(json.dumps({"objective": objective, "point": list(point), "points": args.points,
                          "episodes": episodes,
                          "slices": [s.as_json() for s in grid]}))
        return 0
    print(f"{objective}, {cfg.episode.horizon:g} s episodes: slices through k = ({point[0]:g}, {point[1]:g}, "
          f"{point[2]:g}), {args.points} x {args.points} points each, to {args.beyond:g} x the range past the bound")
    for s in grid:
        i, j = s.axes
        bi, bj, bJ = s.best()
        ii, ij, iJ = s.best_inside()
        minima = s.minima()
        print(f"  {s.label()}: {len(minima)} local minim{'um' if len(minima) == 1 else 'a'}; lowest J "
              f"{bJ:.6e} at {NAMES[i]} = {bi:.1f}, {NAMES[j]} = {bj:.1f}"
              + ("" if (ii, ij) == (bi, bj) else
                 f" (outside the box; in the box {iJ:.6e} at {NAMES[i]} = {ii:.1f}, {NAMES[j]} = {ij:.1f})"))
    if args.plot:
        print(f"wrote {args.plot}")
    return 0
