"""Bags in, estimates and files out: what ``has-control identify`` does."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from has_control.bag.base import warn
from has_control.identify.data import experiment_from_bag
from has_control.identify.fit import IdentificationResult, apply_verdict, identify
from has_control.identify.params_out import excluded_by_adaptation, params_yaml
from has_control.identify.parameters import DEFAULT_KEYS
from has_control.identify.structures import Selection, select_structure
from has_control.identify.validate import Validation, validate
from has_control.common.files import write_atomic
from has_control.plots.identification import plot_validation


@dataclass
class IdentifyOutput:
    result: IdentificationResult
    params: Path | None
    validation: Validation | None
    figure: Path | None
    selection: Selection | None = None


def identify_bags(bags, estimate=None, configs=(), bounds=None, tolerance: float = 0.02,
                  max_evaluations: int = 200, out=None, validate_bag=None, plot=None,
                  structure: str = "auto", reading=None) -> IdentifyOutput:
    """Identify the plant from the runs in ``bags`` (their parameters
    overridden by ``configs``): with ``structure`` "auto" (and no
    ``estimate``), the model class chosen among the candidate structures
    (:mod:`.structures`); else ``estimate`` (default
    :data:`~.parameters.DEFAULT_KEYS`) in the configured plant's structure.
    Write the params file ``out``; validate on ``validate_bag`` (figure
    ``plot``). Nothing is written unless the fit converged. ``reading``: how
    a ros2_control layout bag is read (:class:`~has_control.bag.recorded.Reading`)."""
    how = {} if reading is None else {"reading": reading}
    exps = [experiment_from_bag(b, configs, **how) for b in bags]
    held = experiment_from_bag(validate_bag, configs, **how) if validate_bag else None
    selection = None
    if structure == "auto" and not estimate:
        selection = select_structure(exps, bounds=bounds, tolerance=tolerance, max_evaluations=max_evaluations,
                                     held=held, validate_fn=lambda h, r: validate(h, r).fit)
        result = selection.chosen.result
        exps = [dataclasses.replace(e, cfg=dataclasses.replace(
            e.cfg, plant=selection.chosen.structure.plant(e.cfg.plant, 0.0))) for e in exps]
    else:
        result = identify(exps, estimate or DEFAULT_KEYS, bounds=bounds, tolerance=tolerance,
                          max_evaluations=max_evaluations)
    val = validate(held, result) if held is not None else None
    if val is not None and result.verdict is not None:
        result = apply_verdict(result, result.verdict.with_held_out(val.fit))
    text = params_yaml(exps[0].cfg, result, note=f"has-control identify {' '.join(map(str, bags))}")
    if out:
        for line in excluded_by_adaptation(exps[0].cfg, result):
            warn(line)
    params = write_atomic(out, text) if out else None
    figure = None
    if val is not None and plot:
        figure = plot_validation(val.t, val.measured, val.simulated, val.fit, plot,
                                 f"Identified plant against {Path(str(val.name)).name} (held out)")
    return IdentifyOutput(result, params, val, figure, selection)
