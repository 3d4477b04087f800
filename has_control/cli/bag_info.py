"""``has-control bag-info``: topics, types, counts and duration of a bag."""
from __future__ import annotations

from has_control.bag import describe, read_bag

HELP = "topics, types, counts and duration of a bag"


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG")


def run(args) -> int:
    print(describe(read_bag(args.bag)))
    return 0
