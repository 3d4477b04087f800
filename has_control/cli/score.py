"""``has-control score``: J, e_max, e_mu, e_sigma of a recorded run, from its bag."""
from __future__ import annotations

import json

from has_control.bag import score_bag
from has_control.bag.recorded import Reading
from has_control.cli.args import add_config, add_json
from has_control.wire.joint_mapping import DEFAULT_COMMAND_TOPIC, DEFAULT_STATE_INTERFACES

HELP = "score a recorded run (J, e_max, e_mu, e_sigma) from its bag"


def add_reading(p) -> None:
    """``--state-interfaces`` and ``--command-topic``: how a ros2_control layout bag is read."""
    p.add_argument("--state-interfaces", nargs=4, metavar=("Y", "YDOT", "P1", "P2"),
                   help="joint/interface of y, y_dot, P1, P2 in /joint_states (ros2_control layout; default: "
                        + " ".join(DEFAULT_STATE_INTERFACES) + ")")
    p.add_argument("--command-topic", metavar="TOPIC",
                   help="the valve command topic (default: .../command, else " + DEFAULT_COMMAND_TOPIC + ")")


def reading_of(args) -> Reading:
    si = getattr(args, "state_interfaces", None)
    return Reading(tuple(si) if si else None, getattr(args, "command_topic", None))


def add_arguments(p) -> None:
    p.add_argument("bag", metavar="BAG", help="bag directory or .mcap file")
    add_config(p, "ros__parameters YAML overriding the parameters stored in the bag")
    add_reading(p)
    add_json(p, "print the keys of simulate --json")


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
