"""``has-control replay``: publish a bag with its timing, or replay its states to a
running controller node (``--controller NODE``) or to this code's controller
built from the bag (``--check-code``)."""
from __future__ import annotations

from has_control.cli.args import at_least, number
from has_control.common.errors import HasControlError

RATE_MIN = 1e-3                     # --rate: slower than this is a stalled replay


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG")
    p.add_argument("--rate", type=at_least(RATE_MIN), default=1.0, metavar="R",
                   help=f"time scale, >= {RATE_MIN:g} (default 1.0)")
    p.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics")
    p.add_argument("--wait-for-subscribers", nargs="?", const=1, type=number(1, 1000, int), metavar="N",
                   help="publish once one of the bag's topics has N subscribers (default 1; up to 60 s), so a "
                        "subscriber started before gets the first message (without: after a fixed 0.5 s)")
    p.add_argument("--controller", nargs="?", const="/controller", metavar="NODE",
                   help="feed the recorded states to the running controller node NODE (default /controller; "
                        "reset first) and compare its commands")
    p.add_argument("--check-code", action="store_true",
                   help="feed the recorded states to a controller built in this process from the bag's "
                        "parameters (a regression check of this code) and compare its commands")
    p.add_argument("--tolerance", type=at_least(0.0), default=0.0, metavar="DU",
                   help="with --controller/--check-code: |du| [m] counted as a match (default 0: bit for bit)")


def run(args) -> int:
    # lazy: rclpy loads only for the commands that run nodes
    from has_control.nodes.replay import replay, replay_controller
    if args.controller is not None or args.check_code:
        if args.wait_for_subscribers is not None:
            raise HasControlError("--wait-for-subscribers: not with --controller/--check-code (they wait for the "
                                  "controller themselves)")
        if args.controller is not None and args.check_code:
            raise HasControlError("--controller and --check-code: one or the other")
        r = replay_controller(args.bag, tolerance=args.tolerance, node=args.controller)
        who = (f"the controller node {args.controller}" if args.controller is not None
               else "an in-process controller built from the bag's parameters")
        print(f"{args.bag}: replayed {r.samples} states to {who}: "
              f"{r.mismatches} mismatches, max |du| = {r.max_abs_diff:.3e} m"
              + (f" (first at sample {r.first_mismatch})" if r.mismatches else ""))
        return 0 if r.mismatches == 0 else 1
    n, secs = replay(args.bag, rate=args.rate, topics=args.topics, subscribers=args.wait_for_subscribers or 0)
    print(f"{args.bag}: published {n} messages in {secs:.2f} s")
    return 0
