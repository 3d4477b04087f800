"""``has-control reproduce``: the paper's experiment over seeds, as a report."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from has_control.cli.args import add_config, check_outputs, load, positive_int
from has_control.cli.tune import tuning_args
from has_control.common.files import check_new_output
from has_control.tuning.reproduce import run_experiment, write_report


def add_arguments(p) -> None:
    p.add_argument("--seeds", type=positive_int, default=10, metavar="N", help="seeds 1..N (default 10)")
    p.add_argument("--out", default="out/reproduce", metavar="DIR", help="report directory")
    add_config(p, "ros__parameters YAML (repeatable)")
    p.add_argument("--force", action="store_true", help="write into DIR even if it is not empty")
    p.add_argument("--particles", type=positive_int, metavar="N", help=argparse.SUPPRESS)
    p.add_argument("--iterations", type=positive_int, metavar="N", help=argparse.SUPPRESS)
    p.set_defaults(duration=None, variant="pso-cp-tvac", seed=None, evaluations=None)


def run(args) -> int:
    check_new_output(args.out, args.force, "directory")
    check_outputs(args, directories=("out",))
    cfg = load(args)
    tuning = tuning_args(args)

    def progress(msg: str) -> None:
        print(f"  {msg}", file=sys.stderr, flush=True)
    rows = run_experiment(args.seeds, tuning, cfg, progress=progress)
    report = write_report(rows, Path(args.out), cfg, tuning.upper)
    print(f"wrote {report} (tables.json and figures beside it)")
    return 0
