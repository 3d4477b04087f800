"""``has-control deploy``: a guarded move from the safe gains to the tuned ones,
watched by the watchdog, with the fall-back, the measured J against the safe
gains' and the predicted one. Three places to deploy to:

* (default) in process, on a simulated machine (its ``--config``);
* ``--plant-node``: the project's plant and controller nodes composed in this
  process (``--config``'s ``plant.*``), the deployment through the
  controller's parameters and the topics, as on a running machine;
* ``--controller NAME``: a running machine whose controller node is ``NAME``
  (e.g. ``/controller``): its ``gains.*`` set through ``set_parameters``,
  the watchdog on the topics of ``--layout`` (has_control: ``<namespace>/command``;
  ros2_control: ``--command-topic``) and the controller's internals."""
from __future__ import annotations

import json

from has_control.cli.args import add_config, add_json, check_outputs, gains_arg, namespace, number
from has_control.config import load_config
from has_control.common.errors import HasControlError
from has_control.wire.joint_mapping import DEFAULT_COMMAND_TOPIC


def _node_name(text: str) -> str:
    """An argparse type: a node's full name (``/controller``, ``sim0/controller``)."""
    return "/" + namespace(text).strip("/")


def add_arguments(p) -> None:
    p.add_argument("--gains", nargs=3, required=True, metavar=("K1", "K2", "K3"), help="the tuned gains [1/s]")
    p.add_argument("--safe", nargs=3, metavar=("K1", "K2", "K3"), default=("150", "158", "162"),
                   help="the gains the machine runs safely [1/s] (default: the paper's manual 150 158 162)")
    p.add_argument("--steps", type=number(1, 100, int), default=4, metavar="N", help="steps (default 4)")
    p.add_argument("--settle", type=number(1e-3, 3600.0), default=1.0, metavar="S",
                   help="seconds on the safe gains before the first step (default 1)")
    p.add_argument("--hold", type=number(1e-3, 3600.0), default=1.0, metavar="S",
                   help="seconds each step is held (default 1)")
    p.add_argument("--hf-rms", type=number(1e-9, 1.0), default=5e-4, metavar="M",
                   help="trip when the command's RMS above 20 Hz exceeds this [m] (default 5e-4)")
    p.add_argument("--stop-share", type=number(1e-6, 1.0), default=0.05, metavar="R",
                   help="trip when this share of the last 20 ms has the spool at its stop (default 0.05)")
    p.add_argument("--e1-max", type=number(1e-9, 1.0), default=0.01, metavar="M",
                   help="trip when |e1| exceeds this [m] (default 0.01)")
    p.add_argument("--measure", type=number(0.0, 3600.0), default=None, metavar="S",
                   help="then compare the safe gains and the gains that held over S s each, and keep the safe "
                        "gains unless the others measured lower (default: one period of --config's reference "
                        "when it is a sine, else 0; 0: no comparison)")
    p.add_argument("--margin", type=number(0.0, 0.99), default=None, metavar="R",
                   help="the held gains are kept only when their J measured below (1 - R) x the safe gains' "
                        "(default 0.1: one period's J varies by about 5 %% on a noisy machine)")
    p.add_argument("--predicted", type=number(0.0), metavar="J", help="the J the tuner predicted: flag a gap over 2x")
    p.add_argument("--record", metavar="DIR", help="write the guarded run as a bag")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--plant-node", action="store_true",
                       help="deploy through the project's plant and controller nodes (composed here) and the topics")
    where.add_argument("--controller", metavar="NAME", type=_node_name,
                       help="deploy to the running controller node NAME (e.g. /controller) through its parameters")
    p.add_argument("--layout", choices=("has_control", "ros2_control"), default="has_control",
                   help="--controller: the topics the machine speaks (default has_control)")
    p.add_argument("--namespace", type=namespace, default=None, help="--controller, has_control layout: the loop's")
    p.add_argument("--command-topic", default=DEFAULT_COMMAND_TOPIC, metavar="TOPIC",
                   help=f"--controller, ros2_control layout: the command topic (default {DEFAULT_COMMAND_TOPIC})")
    p.add_argument("--timeout", type=number(1.0, 86400.0), default=60.0, metavar="S",
                   help="--controller: give up when the plan has not run within S s of wall time (default 60)")
    add_config(p, "ros__parameters YAML of the machine (plant.*) and the run (repeatable)")
    add_json(p)


def run(args) -> int:
    # lazy: the deployment's kernels load numba's compiled code (~1 s); --help should not wait
    from has_control.deploy.guarded import DeploymentPlan, deploy_in_process, reference_period
    from has_control.deploy.watchdog import WatchdogLimits
    check_outputs(args, directories=("record",))
    cfg = load_config(args.config or [])
    measure = args.measure if args.measure is not None else (reference_period(cfg) or 0.0)
    plan = DeploymentPlan(gains_arg(args.safe, "--safe"), gains_arg(args.gains), args.steps, args.settle, args.hold,
                          measure, *(() if args.margin is None else (args.margin,)))
    limits = WatchdogLimits(hf_rms=args.hf_rms, stop_share=args.stop_share, e1_max=args.e1_max,
                            valve_limit=cfg.plant.valve_limit)
    if args.plant_node or args.controller:
        return _through_ros(args, cfg, plan, limits)
    try:
        res = deploy_in_process(cfg, plan, limits, args.predicted, keep_trace=bool(args.record))
    except ValueError as exc:
        raise HasControlError(str(exc)) from None
    if args.record:
        _record(args.record, res, cfg)
    if args.json:
        print(json.dumps(res.as_json()))
    else:
        print("\n".join(res.lines()))
        if args.record:
            print(f"wrote {args.record}")
    return 0


def _record(directory, res, cfg) -> None:
    # lazy: the bag writer and the episode module, only with --record
    from has_control.bag import BagWriter, PARAMETERS_KEY, parameters_json, write_trace
    from has_control.config import with_horizon
    from has_control.core.cost import Score
    from has_control.core.episode import Trace
    from has_control.core.params import Gains
    cfg = with_horizon(cfg, max(cfg.episode.horizon, res.plan.duration()))
    w = BagWriter(directory, {PARAMETERS_KEY: parameters_json(cfg)})
    write_trace(w, Trace(res.trace[:, :12].copy(), Score(res.J, 0.0, 0.0, 0.0, len(res.trace), False),
                         Gains(*res.final_gains)), cfg)
    w.close()


def _through_ros(args, cfg, plan, limits) -> int:
    """--plant-node or --controller: the deploy node (has_control.nodes.deploy_node)."""
    # lazy: rclpy and the nodes load only for a deployment through ROS
    from rclpy.experimental import EventsExecutor
    from has_control.deploy.watched import Watched
    from has_control.nodes.deploy_node import deploy_on_plant_node, deploy_on_running_machine
    from has_control.nodes.runtime import borrowed_context
    with borrowed_context() as context:
        try:
            if args.plant_node:
                res, _ = deploy_on_plant_node(cfg, plan, limits, context=context, record=args.record,
                                              predicted_J=args.predicted)
            else:
                watched = Watched(args.layout, args.namespace or "", args.controller, args.command_topic)
                executor = EventsExecutor(context=context)
                res = deploy_on_running_machine(plan, limits, cfg, watched, executor, {"context": context},
                                                record=args.record, predicted_J=args.predicted,
                                                predicted_horizon=cfg.episode.horizon, timeout=args.timeout)
                executor.shutdown()
        except (TimeoutError, ValueError) as exc:
            raise HasControlError(f"deploy: {exc}") from None
    if args.json:
        print(json.dumps(res.as_json()))
    else:
        print("\n".join(res.lines()))
    return 0
