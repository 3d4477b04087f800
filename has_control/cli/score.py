"""``has-control score``: J, e_max, e_mu, e_sigma of a recorded run, from its bag."""
from __future__ import annotations

import json

from has_control.bag import score_bag
from has_control.bag.base import warnings_as_lines
from has_control.cli.args import add_config, add_json, add_reading, reading_of


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG", help="bag directory or .mcap file")
    add_config(p, "ros__parameters YAML overriding the parameters stored in the bag")
    add_reading(p)
    add_json(p, "print the keys of simulate --json")


@warnings_as_lines()
def run(args) -> int:
    score, recorded = score_bag(args.bag, args.config or [], reading=reading_of(args))
    if args.json:
        print(json.dumps(score.as_json()))
    else:
        ep = recorded.cfg.episode
        print(f"{args.bag}: {score.samples} samples of {ep.step * 1e3:g} ms{' (diverged)' if score.diverged else ''}")
        print(f"J = {score.J:.6e}   over {ep.skip_start:g} s .. {ep.horizon - ep.skip_end:g} s: "
              f"e_max = {score.e_max:.4e} m, e_mu = {score.e_mu:.4e} m, e_sigma = {score.e_sigma:.4e} m")
    return 0
