"""``has-control``: the command-line front end.

Every sub-command calls the library; bad input ends with one line on stderr
naming the culprit and exit status 2.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from .errors import HasControlError

EXIT_USAGE = 2


def _gains_arg(values) -> tuple[float, float, float]:
    out = []
    for name, v in zip(("K1", "K2", "K3"), values):
        try:
            x = float(v)
        except ValueError:
            raise HasControlError(f"--gains: {name} = {v!r}: expected a number") from None
        if not (math.isfinite(x) and x > 0):
            raise HasControlError(f"--gains: {name} = {v!r}: must be a finite number > 0")
        out.append(x)
    return tuple(out)


def _load(args):
    from .config import load_config
    from .episode import with_horizon
    cfg = load_config(args.config or [])
    return with_horizon(cfg, args.duration)


def _write_trace_csv(trace, path: str) -> None:
    from .episode import TRACE_COLUMNS
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(p, trace.data, delimiter=",", header=",".join(TRACE_COLUMNS), comments="", fmt="%.17g")


def cmd_simulate(args) -> int:
    from .episode import simulate
    from .params import MANUAL_GAINS
    cfg = _load(args)
    gains = _gains_arg(args.gains) if args.gains else MANUAL_GAINS.as_tuple()
    trace = simulate(cfg, gains)
    s = trace.score
    if args.trace:
        _write_trace_csv(trace, args.trace)
    if args.plot:
        from .plots import plot_tracking
        plot_tracking([(f"k = ({gains[0]:g}, {gains[1]:g}, {gains[2]:g})", trace)], args.plot)
    if args.json:
        print(json.dumps(s.as_json()))
    else:
        ep = cfg.episode
        print(f"gains k = ({gains[0]:g}, {gains[1]:g}, {gains[2]:g}), {s.samples} samples of "
              f"{ep.step * 1e3:g} ms{' (diverged)' if s.diverged else ''}")
        print(f"J = {s.J:.6e}   over {ep.skip_start:g} s .. {ep.horizon - ep.skip_end:g} s: "
              f"e_max = {s.e_max:.4e} m, e_mu = {s.e_mu:.4e} m, e_sigma = {s.e_sigma:.4e} m")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="has-control", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="run one episode with one gain set and print its score")
    s.add_argument("--gains", nargs=3, metavar=("K1", "K2", "K3"),
                   help="back-stepping gains [1/s] (default: the paper's manual 150 158 162)")
    s.add_argument("--duration", type=float, metavar="S", help="horizon [s] (default: config, 10 s)")
    s.add_argument("--config", action="append", metavar="FILE",
                   help="ros__parameters YAML overriding the shipped config (repeatable)")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--plot", metavar="FILE.png", help="write tracking and error figures")
    s.add_argument("--trace", metavar="FILE.csv", help="write the time series")
    s.set_defaults(func=cmd_simulate)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except HasControlError as exc:
        print(f"has-control: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("has-control: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
