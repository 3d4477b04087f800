"""``has-control robustness``: gain sets on every scenario of a set, and their aggregates."""
from __future__ import annotations

import json

from has_control.cli.args import (add_config, add_duration, add_json, batch, dask_spec, figure_path, gains_arg,
                                  check_outputs, load)
from has_control.common.errors import HasControlError
from has_control.common.files import write_atomic
from has_control.config import load_scenarios
from has_control.core.scenarios import parse_aggregate
from has_control.tuning.robustness import robustness_table


def add_arguments(p) -> None:
    p.add_argument("--gains", nargs=3, action="append", required=True, metavar=("K1", "K2", "K3"),
                   help="a gain set [1/s] (repeatable)")
    p.add_argument("--label", action="append", metavar="NAME", help="a name for each --gains, in order")
    p.add_argument("--scenarios", required=True, metavar="FILE", help="scenario YAML file")
    p.add_argument("--aggregate", default="cvar:0.2", metavar="HOW",
                   help="the tail shown beside mean and max: cvar:ALPHA (default cvar:0.2), mean or max")
    add_config(p, "ros__parameters YAML (repeatable)")
    add_duration(p)
    p.add_argument("--dask", type=dask_spec, metavar="SPEC", help="evaluate on a Dask cluster (see tune)")
    p.add_argument("--plot", type=figure_path, metavar="FILE.png",
                   help="write each gain set's J relative to the baseline's, per scenario, as a figure")
    p.add_argument("--baseline", metavar="NAME", help="with --plot: the --label J is relative to (default: the first)")
    p.add_argument("--markdown", metavar="FILE.md", help="write the table as Markdown")
    add_json(p)


def run(args) -> int:
    check_outputs(args, files=("plot", "markdown"))
    cfg = load(args)
    gains = [gains_arg(g) for g in args.gains]
    labels = list(args.label or [])
    if len(labels) > len(gains):
        raise HasControlError(f"--label {labels[len(gains)]}: more labels than --gains")
    labels += [f"k = ({g[0]:g}, {g[1]:g}, {g[2]:g})" for g in gains[len(labels):]]
    if args.baseline is not None and args.baseline not in labels:
        raise HasControlError(f"--baseline {args.baseline}: no gain set has that --label ({', '.join(labels)})")
    scenarios = load_scenarios(args.scenarios, cfg)
    with batch(args) as evaluator:
        table = robustness_table(gains, labels, cfg, scenarios, parse_aggregate(args.aggregate), evaluator)
    print(json.dumps(table.as_json()) if args.json else table.text(), flush=True)    # kept if a write fails
    if args.plot:
        # lazy: matplotlib takes about 1 s to load; only --plot needs it
        from has_control.plots.figures import plot_robustness
        plot_robustness(table, args.plot, args.baseline)
    if args.markdown:
        write_atomic(args.markdown, table.markdown())
    return 0
