"""``has-control``: the command-line front end.

Every sub-command calls the library; bad input ends with one line on stderr
naming the culprit and exit status 2.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from pathlib import Path

from has_control.common.errors import HasControlError

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
RATE_MIN = 1e-3                     # replay --rate: slower than this is a stalled replay


def _gains_arg(values) -> tuple[float, float, float]:
    """--gains K1 K2 K3, checked as the config checks gains.k1..k3."""
    from has_control.config import check_gain, finite_number
    out = []
    for name, v in zip(("K1", "K2", "K3"), values):
        try:
            x = finite_number(float(v))
        except ValueError:
            x = "expected a number"
        why = x if isinstance(x, str) else check_gain(x)
        if why:
            raise HasControlError(f"--gains: {name} = {v!r}: {why}")
        out.append(x)
    return tuple(out)


def _load(args):
    from has_control.config import load_config
    from has_control.config import with_horizon
    cfg = load_config(args.config or [])
    return with_horizon(cfg, args.duration)


def _write_trace_csv(trace, path: str) -> None:
    import numpy as np

    from has_control.core.episode import TRACE_COLUMNS
    from has_control.common.files import write_atomic
    write_atomic(path, lambda tmp: np.savetxt(tmp, trace.data, delimiter=",", header=",".join(TRACE_COLUMNS),
                                              comments="", fmt="%.17g"))


def cmd_simulate(args) -> int:
    from has_control.core.episode import simulate
    from has_control.core.params import MANUAL_GAINS
    cfg = _load(args)
    gains = _gains_arg(args.gains) if args.gains else MANUAL_GAINS.as_tuple()
    trace = simulate(cfg, gains)
    s = trace.score
    if args.trace:
        _write_trace_csv(trace, args.trace)
    if args.plot:
        from has_control.plots.figures import plot_tracking
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


class StatusLine:
    """One self-rewriting status line on a terminal (stderr); silent when piped."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty()
        self.used = False

    def show(self, text: str) -> None:
        if self.enabled:
            self.stream.write(f"\r{text} ")
            self.stream.flush()
            self.used = True

    def close(self) -> None:
        if self.used:
            self.stream.write("\n")


class Progress(StatusLine):
    """A tuning run's progress bar on a terminal."""

    def __init__(self, stream=None):
        super().__init__(stream)
        self.t0 = None

    def __call__(self, swarm) -> None:
        import time
        if not self.enabled:
            return
        now = time.perf_counter()
        self.t0 = self.t0 or now - 1e-9
        rate = swarm.evaluations / max(now - self.t0, 1e-9)
        filled = int(30 * swarm.progress())
        self.show(f"{swarm.name} seed {swarm.seed} [{'#' * filled}{'.' * (30 - filled)}] "
                  f"{swarm.evaluations} evaluations  best J {swarm.gbest_f:.6e}  {rate:,.0f} eval/s")


def _tuning_args(args):
    from has_control.tuning.tuner import load_tuning
    t = load_tuning(args.config or [])
    changes = {k: v for k, v in (("variant", args.variant), ("seed", args.seed),
                                 ("particles", args.particles), ("iterations", args.iterations),
                                 ("evaluations", getattr(args, "evaluations", None)))
               if v is not None}
    try:
        t = t.replace(**changes)
    except HasControlError as exc:
        raise HasControlError(f"command line: {exc}") from None
    _check_method_options(args, t.method)
    return t


def _check_method_options(args, method: str) -> None:
    """--particles/--iterations belong to the swarms, --evaluations to cma-restarts."""
    from has_control.tuning.methods import is_swarm
    swarm = is_swarm(method)
    for option, value, ok in (("--particles", args.particles, swarm), ("--iterations", args.iterations, swarm),
                              ("--evaluations", getattr(args, "evaluations", None), not swarm)):
        if value is not None and not ok:
            raise HasControlError(f"{option} {value}: not an option of the method {method} "
                                  f"({'--particles/--iterations are' if swarm else '--evaluations is'})"
                                  + ("" if swarm else "; --variant pso-cp-tvac for the paper's swarm"))


def _robust(args, cfg, tuning):
    """``tuning`` with the scenarios of ``--scenarios`` and ``--aggregate``."""
    from has_control.core.scenarios import parse_aggregate
    from has_control.config import load_scenarios
    if args.aggregate and not args.scenarios:
        raise HasControlError(f"--aggregate {args.aggregate}: needs --scenarios FILE")
    if not args.scenarios:
        return tuning
    return tuning.replace(scenarios=load_scenarios(args.scenarios, cfg),
                          aggregate=parse_aggregate(args.aggregate or "mean"))


def _batch(args):
    """The batch evaluator of ``--dask SPEC`` (a context manager), else the local one (None)."""
    from contextlib import nullcontext
    if not getattr(args, "dask", None):
        return nullcontext(None)
    from has_control.tuning.dask_evaluator import dask_batch
    return dask_batch(args.dask)


def cmd_tune(args) -> int:
    from has_control.tuning.session import run_session
    if args.resume:
        if args.out and Path(args.out) != Path(args.resume):
            raise HasControlError(f"--out {args.out}: a resumed session writes to its own directory {args.resume}")
        if args.scenarios or args.aggregate:
            raise HasControlError("--scenarios/--aggregate: a resumed session scores on its own scenarios")
        cfg = tuning = None
    else:
        cfg = _load(args)
        tuning = _robust(args, cfg, _tuning_args(args))
    progress = Progress()

    def artefacts(res, directory: Path) -> None:
        from has_control.plots.figures import plot_convergence, plot_gains
        plot_convergence([(res.variant, res.result)], directory / "convergence.png")
        plot_gains(res.result, directory / "gains.png", f"{res.variant}, seed {res.seed}")
    try:
        with _batch(args) as batch:
            run = run_session(cfg, tuning, args.out, resume_dir=args.resume, replace=args.force,
                              on_iteration=progress, artefacts=artefacts, batch=batch,
                              evaluator="dask" if args.dask else "batch",
                              announce=lambda m: print(m, file=sys.stderr))
    finally:
        progress.close()
    res, out = run.result, run.out
    if args.json:
        print(json.dumps(out))
    else:
        k = res.gains
        robust = f" ({res.aggregate} over {res.scenarios} scenarios)" if res.scenarios else ""
        print(f"{res.variant}, seed {res.seed}: k = ({k[0]:.2f}, {k[1]:.2f}, {k[2]:.2f}), "
              f"J = {res.result.fun:.6e}{robust} after {res.result.nit} iterations, "
              f"{res.result.nfev} evaluations, {res.seconds:.1f} s ({res.result.message})")
        for line in res.bounds.lines() if res.bounds is not None else ():
            print(line)
        if run.directory:
            print(f"wrote {run.directory / 'tune.json'}, gains.yaml (a --params-file for the controller), "
                  f"convergence.png, gains.png and the session bag {run.bag}")
    return 0


def cmd_robustness(args) -> int:
    from has_control.tuning.robustness import robustness_table
    from has_control.core.scenarios import parse_aggregate
    from has_control.config import load_scenarios
    cfg = _load(args)
    gains = [_gains_arg(g) for g in args.gains]
    labels = list(args.label or [])
    if len(labels) > len(gains):
        raise HasControlError(f"--label {labels[len(gains)]}: more labels than --gains")
    labels += [f"k = ({g[0]:g}, {g[1]:g}, {g[2]:g})" for g in gains[len(labels):]]
    scenarios = load_scenarios(args.scenarios, cfg)
    with _batch(args) as batch:
        table = robustness_table(gains, labels, cfg, scenarios, parse_aggregate(args.aggregate), batch)
    if args.plot:
        from has_control.plots.figures import plot_robustness
        plot_robustness(table, args.plot)
    if args.markdown:
        from has_control.common.files import write_atomic
        write_atomic(args.markdown, table.markdown())
    print(json.dumps(table.as_json()) if args.json else table.text())
    return 0


def cmd_reproduce(args) -> int:
    from has_control.common.files import check_new_output
    from has_control.tuning.reproduce import run_experiment, write_report
    check_new_output(args.out, args.force, "directory")
    cfg = _load(args)
    tuning = _tuning_args(args)

    def progress(msg: str) -> None:
        print(f"  {msg}", file=sys.stderr, flush=True)
    rows = run_experiment(args.seeds, tuning, cfg, progress=progress)
    report = write_report(rows, Path(args.out), cfg, tuning.upper)
    print(f"wrote {report} (tables.json and figures beside it)")
    return 0


def cmd_stack(args) -> int:
    from has_control import quiet_interrupts
    with quiet_interrupts():                  # rclpy and the nodes' kernels load here
        from has_control.wire.steps import warm_up
        from has_control.nodes.stack import run_stack
        warm_up()
    cfg = _load(args)
    gains = _gains_arg(args.gains) if args.gains else None
    if args.tune:
        if args.foxglove is not None:
            raise HasControlError("--foxglove: not with --tune (the live view serves one run)")
        return _stack_tune(args, cfg)
    record = _new_bag_path(args.record) if args.record else None
    mode = "realtime" if args.realtime else "lock-step"
    line = StatusLine() if cfg.episode.horizon > 3.0 else None

    def progress(done: int, total: int, rate: float) -> None:
        line.show(f"stack ({mode}): {done:,} of {total:,} samples, {rate:,.0f} samples/s")
    try:
        run = run_stack(cfg, gains, namespace=args.namespace or "", publish_internals=True, record=record,
                        realtime=args.realtime, progress=progress if line and line.enabled else None,
                        foxglove=args.foxglove)
    finally:
        if line:
            line.close()
    s, f = run.score, run.loop
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
        if run.bag:
            print(f"recorded {run.bag}")
        if args.foxglove is not None:
            print(f"served live on ws://127.0.0.1:{args.foxglove} (closed)")
    return 0


def _new_bag_path(text: str) -> Path:
    p = Path(text)
    if p.exists():
        raise HasControlError(f"--record {text}: exists already; a bag is never overwritten")
    return p


def _stack_tune(args, cfg) -> int:
    from has_control.nodes.stack import run_tuning_stack
    changes = {k: v for k, v in (("seed", args.seed), ("particles", args.particles),
                                 ("iterations", args.iterations), ("variant", args.variant),
                                 ("evaluations", args.evaluations)) if v is not None}
    from has_control.tuning.tuner import load_tuning
    _check_method_options(args, args.variant or load_tuning(args.config or []).method)
    out = run_tuning_stack(cfg, changes, config_files=args.config or [], evaluator=args.evaluator,
                           namespaces=args.lanes, record=args.record, validate_best=True)
    if args.json:
        print(json.dumps(out))
    else:
        k = out["gains"]
        print(f"tuner ({out['variant']}, {out['evaluator']} evaluator, seed {out['seed']}): "
              f"best k = ({k[0]:.2f}, {k[1]:.2f}, {k[2]:.2f}), J = {out['J']:.6e} after "
              f"{out['iterations']} iterations, {out['evaluations']} evaluations, {out['seconds']:.1f} s")
        if "bounds" in out:
            from has_control.tuning.bounds import BoundDiagnostics
            for line in BoundDiagnostics.from_json(out["bounds"]).lines():
                print(line)
        v = out.get("validation")
        if v:
            print(f"validated through the graph: J = {v['J']:.6e}, e_max = {v['e_max']:.4e} m"
                  + (f", from {out['validation_bag']}" if out.get("validation_bag") else ""))
        print(f"controller gains now ({', '.join(f'{g:.2f}' for g in out['controller_gains'])})")
    return 0


def cmd_score(args) -> int:
    from has_control.bag import score_bag
    score, run = score_bag(args.bag, args.config or [])
    if args.json:
        print(json.dumps(score.as_json()))
    else:
        ep = run.cfg.episode
        print(f"{args.bag}: {score.samples} samples of {ep.step * 1e3:g} ms{' (diverged)' if score.diverged else ''}")
        print(f"J = {score.J:.6e}   over {ep.skip_start:g} s .. {ep.horizon - ep.skip_end:g} s: "
              f"e_max = {score.e_max:.4e} m, e_mu = {score.e_mu:.4e} m, e_sigma = {score.e_sigma:.4e} m")
    return 0


def cmd_bag_info(args) -> int:
    from has_control.bag import describe, read_bag
    print(describe(read_bag(args.bag)))
    return 0


def cmd_replay(args) -> int:
    from has_control.nodes.replay import replay, replay_controller
    if args.controller:
        r = replay_controller(args.bag, tolerance=args.tolerance)
        print(f"{args.bag}: replayed {r.samples} states to a live controller: "
              f"{r.mismatches} mismatches, max |du| = {r.max_abs_diff:.3e} m"
              + (f" (first at sample {r.first_mismatch})" if r.mismatches else ""))
        return 0 if r.mismatches == 0 else 1
    n, secs = replay(args.bag, rate=args.rate, topics=args.topics)
    print(f"{args.bag}: published {n} messages in {secs:.2f} s")
    return 0


NODES = {"plant": "plant_node", "controller": "controller_node", "tuner": "tuner_node"}


def run_node(name: str, ros_args: list[str]) -> int:
    """Run one node as this process (for machines without the ros2 command);
    everything after the node's name goes to ROS (``--ros-args -p k:=v ...``)."""
    from importlib import import_module
    import_module(f"has_control.nodes.{NODES[name]}").main(args=[f"has-control {name}", *ros_args])
    return 0


def _at_least(low: float, kind: type = float):
    """An argparse type: a finite number (``kind`` int: a whole number) >= ``low``."""
    expected = "a whole number" if kind is int else "a number"

    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}") from None
        if not ((kind is int or math.isfinite(v)) and v >= low):
            raise argparse.ArgumentTypeError(f"{text!r}: must be {expected} >= {low:g}")
        return v
    return parse


_positive_int = _at_least(1, int)


_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
_NAMESPACE = re.compile(rf"/?(?:{_NAME}(?:/{_NAME})*)?")


def _namespace(text: str) -> str:
    """An argparse type: a ROS namespace (``/sim0``, ``sim0/a``; tokens of
    letters, digits and underscores, not starting with a digit)."""
    if not _NAMESPACE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r}: not a ROS namespace (tokens of letters, digits and _, "
                                         "not starting with a digit, separated by /)")
    return text


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a port 1..65535") from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a port 1..65535")
    return v


def _figure_path(text: str) -> str:
    """An argparse type: a figure file whose format matplotlib writes (checked before the run)."""
    from has_control.common.errors import HasControlError
    from has_control.plots.figures import figure_format
    try:
        figure_format(text)
    except HasControlError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _dask_spec(text: str) -> str:
    """An argparse type: ``local:N`` or ``tcp://HOST:PORT`` (checked by :mod:`has_control.tuning.dask_evaluator`)."""
    from has_control.tuning.dask_evaluator import parse_spec
    return parse_spec(text)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage block) and exit status 2."""

    def error(self, message):
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    from has_control.tuning.methods import METHODS as VARIANTS
    p = _Parser(prog="has-control", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    s = sub.add_parser("simulate", help="run one episode with one gain set and print its score")
    s.add_argument("--gains", nargs=3, metavar=("K1", "K2", "K3"),
                   help="back-stepping gains [1/s] (default: the paper's manual 150 158 162)")
    s.add_argument("--duration", type=float, metavar="S", help="horizon [s] (default: config, 10 s)")
    s.add_argument("--config", action="append", metavar="FILE",
                   help="ros__parameters YAML overriding the shipped config (repeatable)")
    s.add_argument("--json", action="store_true", help="print one JSON object")
    s.add_argument("--plot", type=_figure_path, metavar="FILE.png", help="write tracking and error figures")
    s.add_argument("--trace", metavar="FILE.csv", help="write the time series")
    s.set_defaults(func=cmd_simulate)

    t = sub.add_parser("tune", help="tune k1, k2, k3 (cma-restarts, or the paper's particle swarms)")
    t.add_argument("--variant", choices=tuple(VARIANTS),
                   help="method (default: config/tuner.yaml, cma-restarts; pso-cp-tvac: the paper's)")
    t.add_argument("--seed", type=int, help="random seed (default 1)")
    t.add_argument("--evaluations", type=_positive_int, metavar="N", help="cma-restarts: budget (default 4000)")
    t.add_argument("--particles", type=_positive_int, metavar="N", help="swarms: swarm size (default 80)")
    t.add_argument("--iterations", type=_positive_int, metavar="N", help="swarms: iterations (default 100)")
    t.add_argument("--config", action="append", metavar="FILE",
                   help="ros__parameters YAML (episode and swarm.* keys; repeatable)")
    t.add_argument("--duration", type=float, metavar="S", help="episode horizon [s] (default 10)")
    t.add_argument("--out", metavar="DIR",
                   help="write the session bag DIR/session (resumable), tune.json, gains.yaml (--params-file), "
                        "convergence.png, gains.png")
    t.add_argument("--resume", metavar="DIR",
                   help="continue the session in DIR from its last complete iteration (its settings apply)")
    t.add_argument("--scenarios", metavar="FILE",
                   help="robust tuning: score each candidate on every scenario of this YAML file")
    t.add_argument("--aggregate", metavar="HOW", help="with --scenarios: mean (default), max or cvar:ALPHA")
    t.add_argument("--dask", type=_dask_spec, metavar="SPEC",
                   help="evaluate on a Dask cluster: local:N (N local workers) or tcp://HOST:PORT (a scheduler)")
    t.add_argument("--force", action="store_true",
                   help="with --out: replace the session and tune.json already in DIR")
    t.add_argument("--json", action="store_true", help="print one JSON object")
    t.set_defaults(func=cmd_tune)

    rb = sub.add_parser("robustness", help="J and e_max of gain sets on every scenario of a set, and their aggregates")
    rb.add_argument("--gains", nargs=3, action="append", required=True, metavar=("K1", "K2", "K3"),
                    help="a gain set [1/s] (repeatable)")
    rb.add_argument("--label", action="append", metavar="NAME", help="a name for each --gains, in order")
    rb.add_argument("--scenarios", required=True, metavar="FILE", help="scenario YAML file")
    rb.add_argument("--aggregate", default="cvar:0.2", metavar="HOW",
                    help="the tail shown beside mean and max: cvar:ALPHA (default cvar:0.2), mean or max")
    rb.add_argument("--config", action="append", metavar="FILE", help="ros__parameters YAML (repeatable)")
    rb.add_argument("--duration", type=float, metavar="S", help="episode horizon [s] (default 10)")
    rb.add_argument("--dask", type=_dask_spec, metavar="SPEC", help="evaluate on a Dask cluster (see tune)")
    rb.add_argument("--plot", type=_figure_path, metavar="FILE.png", help="write J and e_max per scenario as a figure")
    rb.add_argument("--markdown", metavar="FILE.md", help="write the table as Markdown")
    rb.add_argument("--json", action="store_true", help="print one JSON object")
    rb.set_defaults(func=cmd_robustness)

    rp = sub.add_parser("reproduce", help="the paper's experiment over seeds, as a report")
    rp.add_argument("--seeds", type=_positive_int, default=10, metavar="N", help="seeds 1..N (default 10)")
    rp.add_argument("--out", default="out/reproduce", metavar="DIR", help="report directory")
    rp.add_argument("--config", action="append", metavar="FILE", help="ros__parameters YAML (repeatable)")
    rp.add_argument("--force", action="store_true", help="write into DIR even if it is not empty")
    rp.add_argument("--particles", type=_positive_int, metavar="N", help=argparse.SUPPRESS)
    rp.add_argument("--iterations", type=_positive_int, metavar="N", help=argparse.SUPPRESS)
    rp.set_defaults(func=cmd_reproduce, duration=None, variant="pso-cp-tvac", seed=None)

    st = sub.add_parser("stack", help="run plant and controller nodes in one process, lock-step or real time")
    st.add_argument("--duration", type=float, metavar="S", help="horizon [s] (default: config, 10 s)")
    st.add_argument("--gains", nargs=3, metavar=("K1", "K2", "K3"), help="gains [1/s] (default: config)")
    st.add_argument("--namespace", type=_namespace, metavar="NS", help="ROS namespace of both nodes, e.g. /sim0")
    st.add_argument("--config", action="append", metavar="FILE", help="ros__parameters YAML (repeatable)")
    st.add_argument("--json", action="store_true", help="print the keys of simulate --json")
    st.add_argument("--record", metavar="DIR", help="record the run to a rosbag2 MCAP bag DIR")
    st.add_argument("--foxglove", nargs="?", type=_port, const=8765, metavar="PORT",
                    help="serve the run's topics live to Foxglove on ws://127.0.0.1:PORT (default 8765)")
    st.add_argument("--realtime", action="store_true",
                    help="pace the loop to wall time (paced lock-step; misses and lateness in --json)")
    st.add_argument("--tune", action="store_true",
                    help="add the tuner node: tune the gains, set the best on the controller")
    st.add_argument("--variant", choices=tuple(VARIANTS), help="with --tune")
    st.add_argument("--seed", type=int, help="with --tune")
    st.add_argument("--evaluations", type=_positive_int, metavar="N", help="with --tune (cma-restarts)")
    st.add_argument("--particles", type=_positive_int, metavar="N", help="with --tune")
    st.add_argument("--iterations", type=_positive_int, metavar="N", help="with --tune")
    st.add_argument("--evaluator", choices=("batch", "graph"), default="batch",
                    help="with --tune: score candidates in-process (batch) or through the nodes (graph)")
    st.add_argument("--lanes", nargs="+", type=_namespace, metavar="NS", default=None,
                    help="with --tune --evaluator graph: plant/controller pairs in these namespaces")
    st.set_defaults(func=cmd_stack)

    sc = sub.add_parser("score", help="score a recorded run (J, e_max, e_mu, e_sigma) from its bag")
    sc.add_argument("bag", metavar="BAG", help="bag directory or .mcap file")
    sc.add_argument("--config", action="append", metavar="FILE",
                    help="ros__parameters YAML overriding the parameters stored in the bag")
    sc.add_argument("--json", action="store_true", help="print the keys of simulate --json")
    sc.set_defaults(func=cmd_score)

    bi = sub.add_parser("bag-info", help="topics, types, counts and duration of a bag")
    bi.add_argument("bag", metavar="BAG")
    bi.set_defaults(func=cmd_bag_info)

    rp2 = sub.add_parser("replay", help="publish a bag with its timing, or replay it to a controller")
    rp2.add_argument("bag", metavar="BAG")
    rp2.add_argument("--rate", type=_at_least(RATE_MIN), default=1.0, metavar="R",
                     help=f"time scale, >= {RATE_MIN:g} (default 1.0)")
    rp2.add_argument("--topics", nargs="+", metavar="TOPIC", help="only these topics")
    rp2.add_argument("--controller", action="store_true",
                     help="feed the recorded states to a live controller and compare its commands")
    rp2.add_argument("--tolerance", type=_at_least(0.0), default=0.0, metavar="DU",
                     help="with --controller: |du| [m] counted as a match (default 0: bit for bit)")
    rp2.set_defaults(func=cmd_replay)

    from has_control.cli import landscape
    ls = sub.add_parser("landscape", help="J over 2-D slices of the gain space: heatmaps, bound and minima marked")
    landscape.add_arguments(ls)
    ls.set_defaults(func=landscape.run)

    for name in NODES:
        sub.add_parser(name, help=f"run the {name} node; what follows goes to ROS (--ros-args -p k:=v ...)")
    return p


def main(argv=None) -> int:
    """The program (``argv`` None: the command line); the exit status."""
    if argv is None:
        try:
            status = main(sys.argv[1:])
        finally:
            _ignore_interrupts()
        if status == EXIT_INTERRUPTED:        # what is left to run is the shutdown: end with the status
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status)
        return status
    argv = list(argv)
    try:
        if argv and argv[0] in NODES:
            return run_node(argv[0], argv[1:])
        args = build_parser().parse_args(argv)
        return args.func(args)
    except HasControlError as exc:
        print(f"has-control: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:
        print(f"has-control: error: {_os_error_line(exc)}", file=sys.stderr)
        return EXIT_USAGE
    except MemoryError:
        print("has-control: error: out of memory", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("has-control: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _ignore_interrupts() -> None:
    """Once the program's status is decided, a Ctrl-C during the interpreter's
    shutdown (numba, rclpy and matplotlib take a while) changes nothing: the
    shutdown restores the default SIGINT action, which would end the process
    silently by the signal instead of with that status. An interrupted
    program leaves without the shutdown (os._exit), which after a
    KeyboardInterrupt in rclpy's care would otherwise re-raise SIGINT."""
    import signal
    import threading
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _os_error_line(exc: OSError) -> str:
    """``PATH: reason`` (both paths of a rename); the path is never left blank."""
    paths = [str(p) for p in (exc.filename, exc.filename2) if p is not None]
    return f"{' -> '.join(paths) or '(path unknown)'}: {exc.strerror or exc}"


if __name__ == "__main__":
    sys.exit(main())
