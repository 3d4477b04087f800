"""``has-control tune``: tune k1, k2, k3, in a resumable session."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from has_control.bag.series import run_series
from has_control.cli.args import (add_config, add_duration, add_json, batch, check_outputs, dask_spec, load,
                                  positive_int)
from has_control.cli.status import Progress
from has_control.common.errors import HasControlError
from has_control.tuning.session import SESSION, run_session
from has_control.tuning.methods import METHODS, is_swarm
from has_control.tuning.requirements import load_requirements
from has_control.tuning.tuner import load_tuning, robust_tuning


def add_arguments(p) -> None:
    p.add_argument("--variant", choices=tuple(METHODS),
                   help="method (default: config/tuner.yaml, cma-restarts; pso-cp-tvac: the paper's)")
    p.add_argument("--seed", type=int, help="random seed (default 1)")
    p.add_argument("--evaluations", type=positive_int, metavar="N", help="cma-restarts: budget (default 4000)")
    p.add_argument("--particles", type=positive_int, metavar="N", help="swarms: swarm size (default 80)")
    p.add_argument("--iterations", type=positive_int, metavar="N", help="swarms: iterations (default 100)")
    add_config(p, "ros__parameters YAML (episode and swarm.* keys; repeatable)")
    add_duration(p)
    p.add_argument("--out", metavar="DIR",
                   help="write the session bag DIR/session (resumable), tune.json, gains.yaml (--params-file), "
                        "convergence.png, gains.png, tracking.png (the validation run)")
    p.add_argument("--resume", metavar="DIR",
                   help="continue the session in DIR from its last complete iteration (its settings apply)")
    p.add_argument("--scenarios", metavar="FILE",
                   help="robust tuning: score each candidate on every scenario of this YAML file")
    p.add_argument("--aggregate", metavar="HOW", help="with --scenarios: mean (default), max or cvar:ALPHA")
    p.add_argument("--requirements", metavar="FILE",
                   help="a machine's requirements (requirements.*: spool travel, e_max, pressures, command "
                        "above a frequency) as the cost instead of the paper's J (config/requirements_machine.yaml)")
    p.add_argument("--dask", type=dask_spec, metavar="SPEC",
                   help="evaluate on a Dask cluster: local:N (N local workers) or tcp://HOST:PORT (a scheduler)")
    p.add_argument("--force", action="store_true", help="with --out: replace the session and tune.json already in DIR")
    add_json(p)


def tuning_args(args):
    """The tuning settings of ``--config`` with the command line's changes."""
    t = load_tuning(args.config or [])
    changes = {k: v for k, v in (("variant", args.variant), ("seed", args.seed),
                                 ("particles", args.particles), ("iterations", args.iterations),
                                 ("evaluations", getattr(args, "evaluations", None)))
               if v is not None}
    try:
        t = t.replace(**changes)
    except HasControlError as exc:
        raise HasControlError(f"command line: {exc}") from None
    check_method_options(args, t.method)
    return t


def check_method_options(args, method: str) -> None:
    """--particles/--iterations belong to the swarms, --evaluations to cma-restarts."""
    swarm = is_swarm(method)
    for option, value, ok in (("--particles", args.particles, swarm), ("--iterations", args.iterations, swarm),
                              ("--evaluations", getattr(args, "evaluations", None), not swarm)):
        if value is not None and not ok:
            raise HasControlError(f"{option} {value}: not an option of the method {method} "
                                  f"({'--particles/--iterations are' if swarm else '--evaluations is'})"
                                  + ("" if swarm else "; --variant pso-cp-tvac for the paper's swarm"))


def _figures(res, directory: Path) -> None:
    # lazy: matplotlib takes about 1 s to load; only a session with --out draws
    from has_control.plots.figures import plot_convergence, plot_gains
    from has_control.plots.run_figure import gains_text, plot_runs, view_of_series
    plot_convergence([(res.variant, res.result)], directory / "convergence.png")
    plot_gains(res.result, directory / "gains.png", f"Figs. 3-5: {res.variant}, seed {res.seed}")
    plot_runs([view_of_series(run_series(directory / SESSION), f"tuned, {gains_text(res.gains)}")],
              directory / "tracking.png", f"{res.variant}, seed {res.seed}: the validation run (session bag)")


def run(args) -> int:
    check_outputs(args, directories=("out",))
    if args.resume:
        if args.out and Path(args.out) != Path(args.resume):
            raise HasControlError(f"--out {args.out}: a resumed session writes to its own directory {args.resume}")
        if args.scenarios is not None or args.aggregate is not None or args.requirements is not None:
            raise HasControlError("--scenarios/--aggregate/--requirements: a resumed session scores on its own "
                                  "scenarios and requirements")
        cfg = tuning = None
    else:
        cfg = load(args)
        tuning = robust_tuning(tuning_args(args), cfg, args.scenarios, args.aggregate)
        if args.requirements is not None:
            if args.dask:
                raise HasControlError(f"--requirements {args.requirements}: scored in process only, not with --dask")
            tuning = tuning.replace(requirements=load_requirements(args.requirements))
    progress = Progress()
    try:
        with batch(args) as evaluator:
            session = run_session(cfg, tuning, args.out, resume_dir=args.resume, replace=args.force,
                                  on_iteration=progress, artefacts=_figures, batch=evaluator,
                                  evaluator="dask" if args.dask else "batch",
                                  announce=lambda m: print(m, file=sys.stderr))
    finally:
        progress.close()
    res, out = session.result, session.out
    if args.json:
        print(json.dumps(out))
    else:
        k = res.gains
        over = f" ({res.aggregate} over {res.scenarios} scenarios)" if res.scenarios else ""
        name = "J_req" if res.answer is not None and "requirements" in res.answer else "J"
        print(f"{res.variant}, seed {res.seed}: k = ({k[0]:.2f}, {k[1]:.2f}, {k[2]:.2f}), "
              f"{name} = {res.result.fun:.6e}{over} after {res.result.nit} iterations, "
              f"{res.result.nfev} evaluations, {res.seconds:.1f} s ({res.result.message})")
        for line in res.bounds.lines() if res.bounds is not None else ():
            print(line)
        for line in res.lines():
            print(line)
        if session.directory:
            print(f"wrote {session.directory / 'tune.json'}, gains.yaml (a --params-file for the controller), "
                  f"convergence.png, gains.png, tracking.png and the session bag {session.bag}")
    return 0
