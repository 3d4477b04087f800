"""``has-control identify``: plant parameters from recorded runs, with their
intervals and identifiability, as a params file; validated on a held-out run."""
from __future__ import annotations

import argparse
import json
import math

from has_control.bag.base import warnings_as_lines
from has_control.cli.args import add_config, add_json, add_reading, check_apart, check_outputs, figure_path, reading_of
from has_control.common.errors import HasControlError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bags", nargs="+", metavar="BAG", help="recorded runs (bag directories or .mcap files)")
    p.add_argument("--estimate", nargs="+", metavar="KEY",
                   help="plant parameters to estimate in the configured plant's structure (default: the "
                        "structure is selected; mass damping bulk_modulus leakage valve_gain valve_time_constant "
                        "with --structure given; also supply_pressure, valve_frequency, valve_damping_ratio, "
                        "friction_coulomb)")
    p.add_argument("--structure", choices=("auto", "given"), default="auto",
                   help="auto (default): fit the candidate model structures (ideal, first- or second-order valve; "
                        "a sample of delay; friction) and choose by BIC and the held-out fit; given: the "
                        "configured plant's structure")
    add_config(p, "ros__parameters YAML overriding the parameters stored in the bags (repeatable)")
    add_reading(p)
    p.add_argument("--bound", nargs=3, action="append", metavar=("KEY", "LOWER", "UPPER"),
                   help="bounds of an estimated parameter [SI] (default: a factor 4 around the model's value)")
    p.add_argument("--tolerance", type=float, default=0.02, metavar="R",
                   help="an identified parameter's 95 %% half-width is at most R of its value (default 0.02)")
    p.add_argument("--max-evaluations", type=int, default=200, metavar="N",
                   help="residual evaluations per least-squares pass before giving up (default 200)")
    p.add_argument("--out", metavar="FILE.yaml", help="write the identified plant as a --params-file")
    p.add_argument("--validate", metavar="BAG", help="simulate the identified plant against this held-out run")
    p.add_argument("--plot", type=figure_path, metavar="FILE.png",
                   help="with --validate: measured against simulated states")
    add_json(p)
    p.set_defaults(func=run)


@warnings_as_lines()
def run(args) -> int:
    # lazy: numba kernels and SciPy load in ~1 s; the other subcommands should not wait for them
    from has_control.identify import identify_bags
    if args.plot and not args.validate:
        raise HasControlError("--plot: needs --validate BAG (it shows the held-out run)")
    check_outputs(args, files=("out", "plot"))
    check_apart(args, outputs=("out", "plot"), inputs=("bags", "validate", "config"))
    if args.max_evaluations < 1:
        raise HasControlError(f"--max-evaluations {args.max_evaluations}: must be >= 1")
    if not (0 < args.tolerance < 1):
        raise HasControlError(f"--tolerance {args.tolerance}: must be in (0, 1)")
    bounds = {}
    for key, lo, hi in args.bound or []:
        if key in bounds:
            raise HasControlError(f"--bound {key} {lo} {hi}: {key} is bounded twice")
        try:
            bounds[key] = (float(lo), float(hi))
        except ValueError:
            raise HasControlError(f"--bound {key} {lo} {hi}: expected two numbers") from None
    out = identify_bags(args.bags, estimate=args.estimate, configs=args.config or [], bounds=bounds,
                        tolerance=args.tolerance, max_evaluations=args.max_evaluations, out=args.out,
                        validate_bag=args.validate, plot=args.plot, structure=args.structure,
                        reading=reading_of(args))
    result, val = out.result, out.validation
    if args.json:
        doc = result.as_json()
        doc["bags"] = list(args.bags)
        doc["out"] = str(out.params) if out.params else None
        doc["validation"] = val.as_json() if val else None
        doc["structure"] = out.selection.as_json() if out.selection else None
        print(json.dumps(finite_json(doc), allow_nan=False, default=_json_default))
        return 0
    if out.selection:
        print(out.selection.table())
    print(table(result, len(args.bags)))
    if out.params:
        print(f"wrote {out.params}")
    if val:
        fits = ", ".join(f"{k} {v:.2f} %" for k, v in val.fit.items())
        print(f"validation on {val.name} (closed loop, identified plant): fit {fits}"
              + (" (the simulation diverged)" if val.diverged else ""))
    if out.figure:
        print(f"wrote {out.figure}")
    return 0


def _json_default(v):
    v = float(v)
    return v if math.isfinite(v) else None


def finite_json(doc):
    """``doc`` with every non-finite float as None (JSON has none; identify's documented value)."""
    if isinstance(doc, dict):
        return {k: finite_json(v) for k, v in doc.items()}
    if isinstance(doc, (list, tuple)):
        return [finite_json(v) for v in doc]
    if isinstance(doc, float) and not math.isfinite(doc):
        return None
    return doc


def _num(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.6g}"


def table(result, experiments: int) -> str:
    """The estimates, their standard errors, 95 % intervals, priors and status, as text."""
    lines = [f"identified from {experiments} experiment{'s' * (experiments != 1)}: {result.segments} segments, "
             f"{result.passes} pass{'es' * (result.passes != 1)}, {result.evaluations} evaluations, "
             f"{result.seconds:.2f} s",
             f"{'parameter':<34}{'estimate':>13}{'std error':>12}  {'95 % interval':<27}{'model':>11}  status"]
    for k, e in result.estimates.items():
        ci = "-" if not math.isfinite(e.lower) else f"[{e.lower:.6g}, {e.upper:.6g}]"
        status = e.status + (f": {e.why}" if e.why else "")
        lines.append(f"{k + ' [' + e.unit + ']':<34}{_num(e.value):>13}{_num(e.std_error):>12}  {ci:<27}"
                     f"{_num(e.prior):>11}  {status}")
    keys, c = result.free, result.correlation
    strong = [f"{keys[i]}/{keys[j]} {c[i, j]:+.2f}" for i in range(len(keys)) for j in range(i + 1, len(keys))
              if math.isfinite(c[i, j]) and abs(c[i, j]) >= 0.5]
    lines.append("correlations |r| >= 0.5: " + (", ".join(strong) if strong else "none"))
    lines.append("residual RMS: " + ", ".join(f"{k} {v:.3g}" for k, v in result.residual_rms.items()))
    v = result.verdict
    if v is not None:
        # lazy: has_control.identify loads the kernels and SciPy; the other subcommands should not wait
        from has_control.identify.verdict import CORRELATION, HELD_OUT_FIT, LAGS, RESIDUAL_RATIO
        lines.append(f"{'residual analysis':<18}" + "".join(f"{c:>12}" for c in v.noise))
        lines.append(f"{'noise level':<18}" + "".join(f"{x:>12.3g}" for x in v.noise.values()))
        lines.append(f"{'RMS / noise':<18}" + "".join(f"{x:>12.3g}" for x in v.ratio.values())
                     + f"   (limit {RESIDUAL_RATIO:g})")
        lines.append(f"{'autocorrelation':<18}" + "".join(f"{x:>+12.3f}" for x in v.autocorrelation.values())
                     + f"   (|r| limit {CORRELATION:g}, lags 1-{LAGS})")
        lines.append(f"{'x-corr. command':<18}" + "".join(f"{x:>+12.3f}" for x in v.cross_correlation.values())
                     + f"   (|r| limit {CORRELATION:g}, lags 1-{LAGS})")
        if v.held_out:
            lines.append(f"{'held-out fit %':<18}" + "".join(f"{x:>12.2f}" for x in v.held_out.values())
                         + f"   (limit {HELD_OUT_FIT:g} %)")
        lines.append(v.line())
    return "\n".join(lines)
