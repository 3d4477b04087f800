"""``has-control plot BAG [BAG ...] [--out FILE] [--window A B]``: recorded runs as one figure.

Any bag with the run's state topic (``…/state``): ``stack --record``, a tuner
session's validation run, a realtime run (samples without a recorded command
are marked), a bag rewritten by ``rosbags-convert``. Several bags overlay,
named by their gains when those differ, else by the bags' names. Every bag is
read and checked before anything is drawn; bad input is one line, exit 2.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from has_control.bag.base import warnings_as_lines
from has_control.cli.args import add_reading, figure_path, number, reading_of
from has_control.common.errors import HasControlError
from has_control.common.files import check_output


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bags", nargs="+", metavar="BAG", help="bag directory or .mcap file (several: overlaid)")
    p.add_argument("--out", type=figure_path, metavar="FILE.png",
                   help="figure file, .png, .pdf or .svg (default: the first bag's name .png, here)")
    p.add_argument("--window", nargs=2, type=number(), metavar=("A", "B"), help="plot only A <= t <= B [s]")
    p.add_argument("--label", action="append", metavar="NAME", help="a legend name for each BAG, in order")
    p.add_argument("--title", metavar="TEXT", help="the figure's title")
    p.add_argument("--config", action="append", metavar="FILE",
                   help="ros__parameters YAML overriding the parameters stored in the bags")
    add_reading(p)


def default_out(bag: str) -> Path:
    """``NAME.png`` in the working directory, NAME the bag's (a .mcap file's stem)."""
    p = Path(bag.rstrip("/"))
    return Path((p.stem if p.suffix == ".mcap" else p.name) or "run").with_suffix(".png")


@warnings_as_lines()
def run(args) -> int:
    # lazy: the bag reader and matplotlib load only once the arguments are good
    from has_control.bag.series import run_series
    from has_control.plots.run_figure import crop, gains_text, plot_runs, view_of_series
    if args.window and not args.window[0] < args.window[1]:
        raise HasControlError(f"--window {args.window[0]:g} {args.window[1]:g}: empty (A must be < B)")
    labels = list(args.label or [])
    if len(labels) > len(args.bags):
        raise HasControlError(f"--label {labels[len(args.bags)]}: more labels than bags")
    out = Path(args.out) if args.out else default_out(args.bags[0])
    try:
        check_output(out, "file")
    except HasControlError as exc:
        raise HasControlError(f"--out: {exc}") from None
    series = [run_series(b, args.config or [], reading=reading_of(args)) for b in args.bags]
    names = _names(args.bags, series, gains_text)
    views = [view_of_series(s, labels[i] if i < len(labels) else names[i]) for i, s in enumerate(series)]
    if args.window:
        views = [crop(v, *args.window) for v in views]
    plot_runs(views, out, args.title or (f"Recorded run {args.bags[0]}" if len(views) == 1 else None))
    print(f"wrote {out}")
    return 0


def _names(paths: list[str], series, gains_text) -> list[str]:
    """Legend names: the gains in force at the end when they tell the runs apart, else the bags' names."""
    finals = [gains_text(s.gains[-1]) if len(s.gains) else "" for s in series]
    if len(series) > 1 and all(finals) and len(set(finals)) == len(finals):
        return finals
    names = [s.name for s in series]
    if len(set(names)) < len(names):
        names = [str(p) for p in paths]
    if len(series) == 1 and finals[0]:
        return [f"{names[0]}, {finals[0]}"]
    return names
