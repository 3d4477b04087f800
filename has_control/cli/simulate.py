"""``has-control simulate``: one episode with one gain set, and its score."""
from __future__ import annotations

import json

import numpy as np

from has_control.cli.args import add_config, add_duration, add_json, check_outputs, figure_path, gains_arg, load
from has_control.common.files import write_atomic
from has_control.core.episode import TRACE_COLUMNS, TRACE_UNITS, simulate
from has_control.core.params import MANUAL_GAINS


def add_arguments(p) -> None:
    p.add_argument("--gains", nargs=3, metavar=("K1", "K2", "K3"),
                   help="back-stepping gains [1/s] (default: the paper's manual 150 158 162)")
    add_duration(p)
    add_config(p)
    add_json(p)
    p.add_argument("--plot", type=figure_path, metavar="FILE.png", help="write tracking and error figures")
    p.add_argument("--trace", metavar="FILE.csv", help="write the time series")


def write_trace_csv(trace, path: str) -> None:
    header = ",".join(f"{c} [{u}]" for c, u in zip(TRACE_COLUMNS, TRACE_UNITS))
    write_atomic(path, lambda tmp: np.savetxt(tmp, trace.data, delimiter=",", header=header,
                                              comments="", fmt="%.17g"))


def run(args) -> int:
    check_outputs(args, files=("plot", "trace"))
    cfg = load(args)
    gains = gains_arg(args.gains) if args.gains else MANUAL_GAINS.as_tuple()
    trace = simulate(cfg, gains)
    s = trace.score
    if args.trace:
        write_trace_csv(trace, args.trace)
    if args.plot:
        # lazy: matplotlib takes about 1 s to load; only --plot needs it
        from has_control.plots.run_figure import plot_runs, view_of_trace
        plot_runs([view_of_trace(trace, cfg)], args.plot, "Simulated run (has-control simulate)")
    if args.json:
        print(json.dumps(s.as_json()))
    else:
        ep = cfg.episode
        print(f"gains k = ({gains[0]:g}, {gains[1]:g}, {gains[2]:g}), {s.samples} samples of "
              f"{ep.step * 1e3:g} ms{' (diverged)' if s.diverged else ''}")
        print(f"J = {s.J:.6e}   over {ep.skip_start:g} s .. {ep.horizon - ep.skip_end:g} s: "
              f"e_max = {s.e_max:.4e} m, e_mu = {s.e_mu:.4e} m, e_sigma = {s.e_sigma:.4e} m")
    return 0
