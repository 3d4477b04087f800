"""Tune the ABC gains (k1, k2, k3) over the batch evaluator with a method of
:mod:`has_control.tuning.methods` (default ``cma-restarts``; the paper's swarms
``pso``, ``pso-cp``, ``pso-cp-tvac``), and diagnose the bounds of the answer.

Depends inward only: the optimisers and episode (evaluator). The tuner
node uses the same :func:`load_tuning` and the same optimisers.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from has_control.config import (
    SEED_RANGE, Scenario, check_gain, check_scenarios, default_config_files, finite_number, is_seed,
    load_scenarios, read_parameter_files, scenario_configs, scenarios_from_json,
)
from has_control.core.episode import evaluate_configs, evaluate_measured
from has_control.core.measures import MEASURES
from has_control.common.errors import ConfigError, shown
from has_control.core.params import Config
from has_control.core.scenarios import Aggregate, parse_aggregate
from has_control.tuning.bounds import BoundDiagnostics, diagnose
from has_control.tuning.methods import DEFAULT, check_method, drive, is_swarm, new_optimiser
from has_control.tuning.requirements import Requirements, report_lines, requirements_from_json
from has_control.tuning.restarts import RestartSettings
from has_control.tuning.vouch import unseen_variants, vouch_line, vouch_report, vouched_cost
from has_control.tuning.optimiser import OptimiseResult, SwarmError
from has_control.tuning.parameters import TUNING_TABLE
from has_control.tuning.swarm import Swarm, SwarmSettings
from has_control.common.json_numbers import to_json

TUNER_FILE = default_config_files()[0].parent / "tuner.yaml"


@dataclass(frozen=True)
class Tuning:
    """A tuning session's settings: the method (``swarm.variant``), the swarm's
    and ``cma-restarts``' settings, the search box and the seed, and what a
    candidate is scored on: the nominal episode, or (robust tuning) the
    ``aggregate`` of its costs over ``scenarios``; with ``requirements`` a
    machine's cost (:mod:`~has_control.tuning.requirements`) in place of
    the paper's J."""

    swarm: SwarmSettings = SwarmSettings(variant=DEFAULT)
    lower: tuple[float, float, float] = (150.0, 150.0, 150.0)
    upper: tuple[float, float, float] = (1200.0, 800.0, 800.0)
    seed: int = 1
    scenarios: tuple[Scenario, ...] = ()
    aggregate: Aggregate = Aggregate()
    restarts: RestartSettings = RestartSettings()
    requirements: Requirements | None = None

    @property
    def method(self) -> str:
        return self.swarm.variant

    @property
    def bounds(self):
        return (np.array(self.lower), np.array(self.upper))

    def replace(self, **changes) -> "Tuning":
        """Override seed, lower, upper, any SwarmSettings field (``variant``: the
        method) or RestartSettings field; validated."""
        top = {k: changes.pop(k) for k in ("seed", "lower", "upper", "scenarios", "aggregate", "requirements")
               if k in changes}
        restart = {k: changes.pop(k) for k in _RESTART_FIELDS if k in changes}
        t = dataclasses.replace(self, swarm=dataclasses.replace(self.swarm, **changes),
                                restarts=dataclasses.replace(self.restarts, **restart), **top)
        check_method(t.swarm.variant)
        pso = t.swarm if is_swarm(t.swarm.variant) else dataclasses.replace(t.swarm, variant="pso")
        pso.validate()
        t.restarts.validate()
        if not is_seed(t.seed):
            raise SwarmError(f"swarm.seed = {shown(t.seed)}: must be a whole number in {SEED_RANGE}", key="seed")
        Swarm(t.bounds, dataclasses.replace(pso, particles=1, iterations=1), 0)    # bounds check
        for name in ("lower", "upper"):
            for i, v in enumerate(getattr(t, name)):
                why = check_gain(v)
                if why:
                    raise SwarmError(f"bounds: swarm.{name}[{i}] = {v:g}: a gain {why}", key=name)
        return t


# each key's type: the tuning settings' table (tuning.parameters), by name without its prefix
_INT_KEYS = {k.split(".", 1)[1] for k, p in TUNING_TABLE.items() if p.type == "int"}
_STR_KEYS = {k.split(".", 1)[1] for k, p in TUNING_TABLE.items() if p.type == "str"}
_LIST_KEYS = {k.split(".", 1)[1] for k, p in TUNING_TABLE.items() if p.type == "double[]"}
_RESTART_FIELDS = {f.name for f in dataclasses.fields(RestartSettings)}
PREFIXES = ("swarm.", "restarts.")       # the keys of config/tuner.yaml


def tuning_from_parameters(flat: Mapping[str, Any], sources: Mapping[str, str] | None = None,
                           base: Tuning | None = None) -> Tuning:
    """Validated :class:`Tuning` from flat ``swarm.*`` and ``restarts.*`` parameters (others ignored)."""
    t = base or Tuning()
    known = {"swarm.": {f.name for f in dataclasses.fields(SwarmSettings)} | {"seed"} | _LIST_KEYS,
             "restarts.": _RESTART_FIELDS}
    changes: dict[str, Any] = {}
    where: dict[str, str] = {}
    for key, value in flat.items():
        prefix = next((p for p in PREFIXES if key.startswith(p)), None)
        if prefix is None:
            continue
        name = key[len(prefix):]
        fields = known[prefix]
        where[name] = (sources or {}).get(key, "parameters")

        def bad(why):
            return ConfigError(f"{where[name]}: {key} = {shown(value)}: {why}")
        if name not in fields:
            raise bad("unknown parameter")
        if name in _INT_KEYS:
            if isinstance(value, bool) or not isinstance(value, int):
                raise bad("expected a whole number")
        elif name in _STR_KEYS:
            if not isinstance(value, str):
                raise bad("expected a string")
        elif name in _LIST_KEYS:
            numbers = [finite_number(v) for v in value] if isinstance(value, (list, tuple)) else []
            if len(numbers) != 3 or any(isinstance(v, str) for v in numbers):
                raise bad("expected a list of three finite numbers")
            value = tuple(numbers)
        else:
            number = finite_number(value)
            if isinstance(number, str):
                raise bad(number)
            value = number
        changes[name] = value
    try:
        return t.replace(**changes)
    except SwarmError as exc:
        culprit = exc.key if exc.key in changes else None
        if exc.key == "bounds":                        # the pair: the file that set either bound
            culprit = next((n for n in ("lower", "upper") if n in changes), None)
        origin = where.get(culprit, "parameters") if culprit else ", ".join(sorted(set(where.values())))
        raise ConfigError(f"{origin}: {exc}") from None


def tuning_parameters(t: Tuning) -> dict[str, Any]:
    """Flat ``swarm.*`` and ``restarts.*`` parameters of a Tuning (inverse of :func:`tuning_from_parameters`)."""
    out = {f"swarm.{k}": v for k, v in dataclasses.asdict(t.swarm).items()}
    out.update({"swarm.seed": t.seed, "swarm.lower": list(t.lower), "swarm.upper": list(t.upper)})
    out.update({f"restarts.{k}": v for k, v in dataclasses.asdict(t.restarts).items()})
    return out


def tuning_json(t: Tuning) -> dict:
    """A Tuning as JSON-ready data (a session bag's settings; inverse: :func:`tuning_from_json`)."""
    d = {"swarm": dataclasses.asdict(t.swarm), "restarts": dataclasses.asdict(t.restarts),
         "lower": list(t.lower), "upper": list(t.upper), "seed": t.seed}
    if t.scenarios:
        d.update(scenarios=[s.as_json() for s in t.scenarios], aggregate=str(t.aggregate))
    if t.requirements is not None:
        d["requirements"] = t.requirements.as_json()
    return d


def tuning_from_json(d: dict, where: str = "tuning settings", cfg: Config | None = None) -> Tuning:
    """A stored Tuning (a session's settings), through the checks the command
    line's settings pass: the ``swarm.*`` parameters as a config file's
    (:func:`tuning_from_parameters`), the scenarios as a scenario file's
    (:func:`~has_control.config.check_scenarios`, over ``cfg``), the
    aggregate as ``--aggregate``'s. One ConfigError line naming ``where``."""
    keys = {"swarm", "lower", "upper", "seed"}
    if (not isinstance(d, dict) or not keys <= set(d) or not isinstance(d["swarm"], dict)
            or not isinstance(d.get("restarts", {}), dict)):
        raise ConfigError(f"{where}: expected an object with {', '.join(sorted(keys))} (and restarts)")
    extra = sorted(set(d) - keys - {"scenarios", "aggregate", "restarts", "requirements"})
    if extra:
        raise ConfigError(f"{where}: {shown(extra[0])}: unknown key")
    if ("aggregate" in d) != ("scenarios" in d):
        raise ConfigError(f"{where}: scenarios and aggregate go together")
    missing = sorted({f.name for f in dataclasses.fields(SwarmSettings)} - set(d["swarm"]))
    if missing:
        raise ConfigError(f"{where}: swarm.{missing[0]}: missing")
    flat = {f"swarm.{k}": v for k, v in d["swarm"].items()}
    flat.update({f"restarts.{k}": v for k, v in d.get("restarts", {}).items()})    # none: the defaults
    flat.update({"swarm.lower": d["lower"], "swarm.upper": d["upper"], "swarm.seed": d["seed"]})
    t = tuning_from_parameters(flat, {k: where for k in flat})
    if "requirements" in d:
        t = t.replace(requirements=requirements_from_json(d["requirements"], f"{where}: requirements"))
    if "scenarios" not in d:
        return t
    scenarios = check_scenarios(scenarios_from_json(d["scenarios"], f"{where}: scenarios"), cfg or Config(),
                                f"{where}: scenarios")
    return t.replace(scenarios=scenarios, aggregate=aggregate_arg(d["aggregate"], f"{where}: aggregate"))


def aggregate_arg(text, name: str) -> Aggregate:
    """:func:`~has_control.core.scenarios.parse_aggregate` of a value given as ``name``."""
    if not isinstance(text, str):
        raise ConfigError(f"{name} = {shown(text)}: expected mean, max or cvar:ALPHA")
    try:
        return parse_aggregate(text)
    except ConfigError as exc:
        raise ConfigError(f"{name}: {exc}") from None


def robust_tuning(tuning: Tuning, cfg: Config, scenarios: str | None, aggregate: str | None,
                  names: tuple[str, str] = ("--scenarios", "--aggregate")) -> Tuning:
    """``tuning`` scored on the scenario file ``scenarios`` with ``aggregate``
    (None: mean), as every front end takes them (``tune``, the tuner node):
    an aggregate without scenarios is refused, an empty one too."""
    agg = aggregate_arg(aggregate, names[1]) if aggregate is not None else None
    if not scenarios:
        if aggregate is not None:
            raise ConfigError(f"{names[1]} {aggregate if len(aggregate) <= 60 else shown(aggregate)}: "
                              f"needs {names[0]} FILE")
        return tuning
    return tuning.replace(scenarios=load_scenarios(scenarios, cfg), aggregate=agg or Aggregate("mean"))


def load_tuning(paths: Iterable[str | Path] = (), defaults: bool = True) -> Tuning:
    """Tuning settings from config/tuner.yaml (if ``defaults``) and ``paths``."""
    files = ([TUNER_FILE] if defaults else []) + [Path(p) for p in paths]
    return tuning_from_parameters(*read_parameter_files(files))


@dataclass
class TuneResult:
    """A finished tuning session: the optimiser's result, what it took, and
    the bound diagnostics of the answer (their probes are not in ``result.nfev``)."""

    variant: str                    # the method
    seed: int
    result: OptimiseResult
    seconds: float
    scenarios: int = 0              # robust tuning: J is the aggregate over this many scenarios
    aggregate: str = ""
    bounds: BoundDiagnostics | None = None
    answer: dict | None = None      # the answer's nominal run: with a travel, a validated band or requirements

    @property
    def gains(self) -> tuple[float, float, float]:
        return tuple(float(v) for v in self.result.x)

    def as_json(self) -> dict:
        """Keys of ``has-control tune --json``."""
        return {"variant": self.variant, "seed": self.seed, "gains": list(self.gains),
                "J": to_json(self.result.fun), "iterations": self.result.nit,
                "evaluations": self.result.nfev, "seconds": self.seconds,
                "success": bool(self.result.success), "message": str(self.result.message),
                "history": [to_json(h.best_cost) for h in self.result.history],
                **({"bounds": self.bounds.as_json()} if self.bounds is not None else {}),
                **({"answer": _finite(self.answer)} if self.answer is not None else {}),
                **({"scenarios": self.scenarios, "aggregate": self.aggregate,
                    "episodes": self.result.nfev * self.scenarios} if self.scenarios else {})}

    def lines(self) -> list[str]:
        """The answer's requirements and the spool-travel warning, one line each (none on the reference)."""
        if self.answer is None:
            return []
        out = report_lines(self.answer.get("requirements", []))
        if "vouch" in self.answer:
            out.append(vouch_line(self.answer["vouch"], self.answer["vouch"]["band_hz"]))
        travel, m = self.answer["valve_limit"], self.answer["measures"]
        if travel > 0.0 and m["u_peak"] > travel:
            out.append(f"warning: the tuned gains' command exceeds the spool travel {travel * 1e3:g} mm on the "
                       f"nominal run: peak {m['u_peak'] * 1e3:.3g} mm, at the stop on {100 * m['at_stop']:.2f} % "
                       "of the samples" + ("" if "requirements" in self.answer else
                                           " (the paper's J rewards commands the valve cannot make: --requirements "
                                           "config/requirements_machine.yaml states the machine's)"))
        return out


def _finite(d):
    if isinstance(d, dict):
        return {k: _finite(v) for k, v in d.items()}
    if isinstance(d, list):
        return [_finite(v) for v in d]
    return to_json(d) if isinstance(d, float) else d


def answer_run(cfg: Config, tuning: Tuning, gains) -> dict | None:
    """The measures (and requirements) of ``gains`` on ``cfg``'s nominal run
    and whether the model vouches for them, when the plant has a spool travel
    or a validated band or the tuning has requirements; else None."""
    variants = unseen_variants(cfg)
    req = tuning.requirements
    inadequate = cfg.plant.model_adequacy == "inadequate"
    if req is None and cfg.plant.valve_limit <= 0.0 and not variants and not inadequate:
        return None
    rows = evaluate_measured(np.array([gains]), [cfg] + [v.cfg for v in variants],
                             **({"corner": req.hf_frequency} if req else {}))[0]
    row = rows[0]
    tracked = req.tracking(rows) if req is not None else rows[:, 0]     # the J the vouch compares
    out = {"valve_limit": float(cfg.plant.valve_limit), "measures": dict(zip(MEASURES, map(float, row[4:])))}
    if req is not None:
        out["requirements"] = req.report(row)
        out["J_requirements"] = float(req.cost(row[None, :])[0])
    if variants or inadequate:
        out["vouch"] = {"band_hz": float(cfg.plant.validated_band),
                        **vouch_report([v.name for v in variants], [v.text for v in variants], float(tracked[0]),
                                       tracked[1:], capped=any(v.capped for v in variants),
                                       inadequate=inadequate)}
    return out


def make_objective(cfg: Config, tuning: Tuning,
                   batch: Callable[[np.ndarray, list], np.ndarray] | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """What a tuning session minimises: (P, 3) gains -> P costs J on ``cfg``'s
    nominal episode, or (robust tuning) the aggregate of J over ``tuning.scenarios``;
    ``batch``: the batch evaluator (default :func:`~has_control.core.episode.evaluate_configs`).
    With ``tuning.requirements`` the cost is the machine's
    (:mod:`~has_control.tuning.requirements`); where the plant states a
    validated band (``plant.validated_band``) a nominal session, in process,
    charges the candidates that rely on what lies above it
    (:mod:`~has_control.tuning.vouch`)."""
    req = tuning.requirements
    if req is not None and batch is not None:
        raise ConfigError("requirements: scored by the in-process evaluator only (not --dask or the graph)")
    variants = [v.cfg for v in unseen_variants(cfg)] if batch is None and not tuning.scenarios else []
    if req is not None:
        def costs(k, cfgs):
            """(the cost on each of ``cfgs``, the J the vouch compares: without the penalties)."""
            runs = evaluate_measured(k, cfgs, corner=req.hf_frequency)
            return req.cost(runs), req.tracking(runs)
    else:
        run = batch or evaluate_configs

        def costs(k, cfgs):
            c = run(k, cfgs)[:, :, 0]
            return c, c
    if tuning.scenarios:
        configs = scenario_configs(cfg, tuning.scenarios)

        def objective(k):
            return tuning.aggregate(costs(k, configs)[0])
    elif variants:
        def objective(k):
            c, tracked = costs(k, [cfg] + variants)
            return vouched_cost(c[:, 0], tracked[:, 1:])
    else:
        def objective(k):
            return costs(k, [cfg])[0][:, 0]
    return objective


def tune(cfg: Config | None = None, tuning: Tuning | None = None,
         callback: Callable[[Any], bool | None] | None = None,
         swarm=None,
         objective: Callable[[np.ndarray], np.ndarray] | None = None,
         batch: Callable[[np.ndarray, list], np.ndarray] | None = None,
         diagnostics: bool = True) -> TuneResult:
    """Run one tuning session with ``tuning.method`` (``swarm``: an optimiser
    of :mod:`~has_control.tuning.methods` to resume), then (``diagnostics``)
    probe the bounds of its answer with the same objective.

    ``objective`` maps the (N, 3) candidate gains to N costs J; by default
    the batch evaluator over ``cfg`` (robust tuning: the aggregate of the
    costs over ``tuning.scenarios``). The tuner node passes one that runs
    every candidate through the node graph. ``batch(gains, cfgs)`` is the
    batch evaluator, with the contract of
    :func:`~has_control.core.episode.evaluate_configs` (default: that function,
    in this process; :mod:`has_control.tuning.dask_evaluator` gives one on Dask).
    """
    cfg = cfg or Config()
    tuning = tuning or Tuning()
    if swarm is None:
        swarm = new_optimiser(tuning.method, tuning.bounds, tuning.swarm, tuning.restarts, tuning.seed)
    if objective is None:
        objective = make_objective(cfg, tuning, batch)
    t0 = time.perf_counter()
    result = drive(swarm, objective, callback)
    seconds = time.perf_counter() - t0
    bounds = None
    if diagnostics and result.success:
        bounds = diagnose(objective, result.x, result.fun, swarm.lower, swarm.upper)
    answer = answer_run(cfg, tuning, result.x) if result.success else None
    return TuneResult(swarm.name, swarm.seed, result, seconds,
                      len(tuning.scenarios), str(tuning.aggregate) if tuning.scenarios else "", bounds, answer)
