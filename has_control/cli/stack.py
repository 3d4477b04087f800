"""``has-control stack``: plant and controller nodes in one process, lock-step
or real time, optionally recorded, served live, or tuned by the tuner node."""
from __future__ import annotations

import json
from pathlib import Path

from has_control.common.interrupts import quiet_interrupts
from has_control.cli.args import add_config, add_json, gains_arg, load, namespace, number, port, positive_int
from has_control.cli.status import StatusLine
from has_control.common.errors import HasControlError
from has_control.cli.tune import check_method_options
from has_control.tuning.bounds import BoundDiagnostics
from has_control.tuning.methods import METHODS
from has_control.tuning.tuner import load_tuning


FOXGLOVE_WAIT_MAX = 3600.0       # [s] --foxglove-wait: an hour is a forgotten run, not a wait


def add_arguments(p) -> None:
    p.add_argument("--duration", type=float, metavar="S", help="horizon [s] (default: config, 10 s)")
    p.add_argument("--gains", nargs=3, metavar=("K1", "K2", "K3"), help="gains [1/s] (default: config)")
    p.add_argument("--namespace", type=namespace, metavar="NS", help="ROS namespace of both nodes, e.g. /sim0")
    add_config(p, "ros__parameters YAML (repeatable)")
    add_json(p, "print the keys of simulate --json")
    p.add_argument("--record", metavar="DIR", help="record the run to a rosbag2 MCAP bag DIR")
    p.add_argument("--foxglove", nargs="?", type=port, const=8765, metavar="PORT",
                   help="serve the run's topics live to Foxglove on ws://127.0.0.1:PORT (default 8765)")
    p.add_argument("--foxglove-wait", type=number(0.0, FOXGLOVE_WAIT_MAX), metavar="S",
                   help=f"with --foxglove: wait up to S seconds (0..{FOXGLOVE_WAIT_MAX:g}) for a client to "
                        "subscribe before the run")
    p.add_argument("--realtime", action="store_true",
                   help="pace the loop to wall time (paced lock-step; misses and lateness in --json)")
    p.add_argument("--tune", action="store_true",
                   help="add the tuner node: tune the gains, set the best on the controller")
    p.add_argument("--variant", choices=tuple(METHODS), help="with --tune")
    p.add_argument("--seed", type=int, help="with --tune")
    p.add_argument("--evaluations", type=positive_int, metavar="N", help="with --tune (cma-restarts)")
    p.add_argument("--particles", type=positive_int, metavar="N", help="with --tune")
    p.add_argument("--iterations", type=positive_int, metavar="N", help="with --tune")
    p.add_argument("--evaluator", choices=("batch", "graph"), default="batch",
                   help="with --tune: score candidates in-process (batch) or through the nodes (graph)")
    p.add_argument("--keep-episodes", action="store_true",
                   help="with --tune --evaluator graph --record DIR: keep one bag per episode under DIR/episodes")
    p.add_argument("--lanes", nargs="+", type=namespace, metavar="NS", default=None,
                   help="with --tune --evaluator graph: plant/controller pairs in these namespaces")


def new_bag_path(text: str) -> Path:
    p = Path(text)
    if p.exists():
        raise HasControlError(f"--record {text}: exists already; a bag is never overwritten")
    return p


def run(args) -> int:
    if args.foxglove_wait is not None and args.foxglove is None:
        raise HasControlError(f"--foxglove-wait {args.foxglove_wait:g}: only with --foxglove (there is no live view "
                              "to wait for)")
    with quiet_interrupts():                  # rclpy and the nodes' kernels load here
        # lazy: rclpy and the nodes' compiled steps load only for the commands that run nodes, under
        # quiet_interrupts so that a Ctrl-C while they load is one line
        from has_control.nodes.stack import run_stack, run_tuning_stack
        from has_control.wire.steps import warm_up
        warm_up()
    cfg = load(args)
    gains = gains_arg(args.gains) if args.gains else None
    if args.tune:
        if args.foxglove is not None:
            raise HasControlError("--foxglove: not with --tune (the live view serves one run)")
        return _tune(args, cfg, run_tuning_stack)
    record = new_bag_path(args.record) if args.record else None
    mode = "realtime" if args.realtime else "lock-step"
    line = StatusLine() if cfg.episode.horizon > 3.0 else None

    def progress(done: int, total: int, rate: float) -> None:
        line.show(f"stack ({mode}): {done:,} of {total:,} samples, {rate:,.0f} samples/s")
    try:
        result = run_stack(cfg, gains, namespace=args.namespace or "", publish_internals=True, record=record,
                           realtime=args.realtime, progress=progress if line and line.enabled else None,
                           foxglove=args.foxglove, foxglove_wait=args.foxglove_wait or 0.0,
                           announce=lambda text: print(text, flush=True))
    finally:
        if line:
            line.close()
    s, f = result.score, result.loop
    if args.json:
        print(json.dumps({**s.as_json(), **f}))
    else:
        k = gains or cfg.gains.as_tuple()
        print(f"stack (plant + controller, {mode}, one process): k = ({k[0]:g}, {k[1]:g}, {k[2]:g}), "
              f"{s.samples} samples at {f['samples_per_second']:,.0f} samples/s "
              f"(real-time factor {f['realtime_factor']:.3f})")
        print(f"J = {s.J:.6e}   e_max = {s.e_max:.4e} m, e_mu = {s.e_mu:.4e} m, e_sigma = {s.e_sigma:.4e} m")
        if args.realtime or f["failsafe_samples"]:
            late = f"{f['late_p99_us']:.0f} us" if f["late_p99_us"] is not None else "n/a"
            print(f"missed {f['missed_samples']} samples, {f['failsafe_samples']} on the fail-safe, "
                  f"lateness p99 {late}")
        if result.bag:
            print(f"recorded {result.bag}")
        if args.foxglove is not None:
            print(f"served live on ws://127.0.0.1:{args.foxglove} (closed)")
    return 0


def _tune(args, cfg, run_tuning_stack) -> int:
    changes = {k: v for k, v in (("seed", args.seed), ("particles", args.particles),
                                 ("iterations", args.iterations), ("variant", args.variant),
                                 ("evaluations", args.evaluations)) if v is not None}
    check_method_options(args, args.variant or load_tuning(args.config or []).method)
    out = run_tuning_stack(cfg, changes, config_files=args.config or [], evaluator=args.evaluator,
                           namespaces=args.lanes, record=args.record, validate_best=True,
                           keep_episodes=args.keep_episodes)
    if args.json:
        print(json.dumps(out))
    else:
        k = out["gains"]
        print(f"tuner ({out['variant']}, {out['evaluator']} evaluator, seed {out['seed']}): "
              f"best k = ({k[0]:.2f}, {k[1]:.2f}, {k[2]:.2f}), J = {out['J']:.6e} after "
              f"{out['iterations']} iterations, {out['evaluations']} evaluations, {out['seconds']:.1f} s")
        if "bounds" in out:
            for line in BoundDiagnostics.from_json(out["bounds"]).lines():
                print(line)
        v = out.get("validation")
        if v:
            print(f"validated through the graph: J = {v['J']:.6e}, e_max = {v['e_max']:.4e} m"
                  + (f", from {out['validation_bag']}" if out.get("validation_bag") else ""))
        if out.get("controller_gains"):
            print(f"controller gains now ({', '.join(f'{g:.2f}' for g in out['controller_gains'])})")
    return 0
