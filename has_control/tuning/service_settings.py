"""The tuner node's settings: its own parameter table and the checks ``~/start`` makes (ROS-free).

The node declares :data:`OWN_PARAMETERS` (and the model's and the tuning's
tables, :data:`TUNER_TABLE` in all) and reads them back through
:func:`settings_from` with a function from a parameter's name to its plain
value: the checks ``has-control tune`` makes, each refusal one
:class:`~has_control.common.errors.ConfigError` line naming the parameter.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

from has_control.common.errors import ConfigError
from has_control.config import CONFIG_TABLE, Param, refusal, table
from has_control.tuning.parameters import TUNING_TABLE
from has_control.tuning.tuner import Tuning, robust_tuning, tuning_from_parameters
from has_control.tuning.validation import VALIDATION_TOLERANCE

#: The model's parameters the tuner takes (the same as plant and controller, by prefix).
PREFIXES = ("actuator.", "simulation.", "gains.", "adaptation.", "reference.", "cost.", "metrics.", "plant.", "noise.")
EVALUATORS = ("graph", "batch")
#: The tuner's own parameters (its table; the model's and the tuning's are CONFIG_TABLE's and TUNING_TABLE's).
OWN_PARAMETERS = table((
    Param("scenarios", "str", "", text="robust tuning: a scenario file scored by the batch evaluator "
          "(empty: the nominal episode)"),
    Param("aggregate", "str", "mean", text="robust tuning: mean | max | cvar:alpha of the scenarios' J"),
    Param("evaluator", "str", "batch", text="batch (in-process, fast) | graph (every candidate through the "
          "lanes' nodes)", choices=EVALUATORS),
    Param("validate_best", "bool", True, text="re-run the best gains through the graph, recorded and scored "
          "from the bag"),
    Param("validation_tolerance", "double", VALIDATION_TOLERANCE, text="the graph's J of the best gains may "
          "differ from the library's by this share of it; more is a disagreement", lower=0.0),
    Param("lanes", "str[]", [""], text="namespaces of the plant/controller pairs ('' is the root)", read_only=True),
    Param("controller", "str", "controller", text="the controller's node name within a lane", read_only=True),
    Param("plant", "str", "plant", text="the plant's node name within a lane", read_only=True),
    Param("record", "str", "", text="a directory: the session bag, gains.yaml and (graph) one bag per episode; "
          "empty: none kept"),
    Param("force", "bool", False, text="record: replace a session the directory holds (else ~/start "
          "refuses)"),
    Param("resume", "str", "", text="a directory of an interrupted session to resume"),
    Param("episode_timeout", "double", 120.0, "s of wall time", "graph: an episode not finished after this long "
          "scores +inf", lower=0.0, lower_open=True),
    Param("log_every", "int", 1, text="log every n-th iteration", lower=1),
    Param("keep_episodes", "bool", False, text="graph: keep one bag per episode under record/episodes (default: "
          "scored, then deleted)"),
    Param("autostart", "bool", True, text="tune at start-up and exit when done (false: wait for ~/start, serve "
          "until shut down)", read_only=True),
    Param("lane_timeout", "double", 30.0, "s", "graph: wait this long for the lanes' plant and controller; with "
          "evaluator batch they are optional (looked for once the tuning is done, the best gains set on them if "
          "found)", lower=0.0, lower_open=True),
))
#: Every parameter the tuner takes, by name.
TUNER_TABLE = {**{k: p for k, p in CONFIG_TABLE.items() if k.startswith(PREFIXES)}, **TUNING_TABLE,
               **OWN_PARAMETERS}


@dataclasses.dataclass(frozen=True)
class Settings:
    """What one session runs with: the parameters as they were at ``~/start``, validated."""

    cfg: object
    tuning: Tuning
    evaluator: str
    record: str | None
    resume: str | None
    force: bool
    episode_timeout: float              # [s of wall time]
    validate: bool
    tolerance: float
    keep_episodes: bool
    log_every: int
    lane_timeout: float                 # [s]


def settings_from(value: Callable[[str], Any], cfg: Callable[[], object], where: str) -> Settings:
    """The session's settings from ``value(name)`` (a parameter's plain value) and
    ``cfg()`` (the model, validated by the core; asked for once the tuner's own
    parameters passed), through the checks ``has-control tune`` makes; a
    ConfigError line names the culprit (``where``: e.g. "parameter of /tuner")."""
    for name in OWN_PARAMETERS:
        reason = refusal(OWN_PARAMETERS, name, value(name))
        if reason is not None:
            raise ConfigError(f"{where}: {reason}")
    model = cfg()
    flat = {k: value(k) for k in TUNING_TABLE}
    tuning = tuning_from_parameters(flat, {k: where for k in flat})
    evaluator = value("evaluator")
    path, how = value("scenarios"), value("aggregate")
    if path and evaluator == "graph":
        raise ConfigError(f"parameter scenarios = {path!r}: needs evaluator batch (the lanes run one plant)")
    # checked as tune's --scenarios/--aggregate; "mean" (the default) without scenarios is the nominal episode
    tuning = robust_tuning(tuning, model, path, how if path or how != "mean" else None,
                           ("parameter scenarios", "parameter aggregate"))
    return Settings(model, tuning, evaluator, value("record") or None, value("resume") or None,
                    bool(value("force")), float(value("episode_timeout")), bool(value("validate_best")),
                    float(value("validation_tolerance")), bool(value("keep_episodes")),
                    int(value("log_every")), float(value("lane_timeout")))
