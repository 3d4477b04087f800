"""The tuning methods by name, one table: ``cma-restarts`` (the default) and the
paper's particle swarms ``pso``, ``pso-cp``, ``pso-cp-tvac``.

Every method is an :class:`~has_control.tuning.optimiser.Optimiser` (ask/tell)
with the same face: ``name``, ``seed``, ``ask()``, ``tell(costs)``, ``done``,
``iteration``, ``evaluations``, ``best_x``, ``best_f`` (``gbest_x``,
``gbest_f``: the older names, still read), ``history``, ``progress()`` (share
of its budget spent), ``state_dict(history)`` / ``from_state(state)`` and
``result()``. :func:`minimize` is the one plain function over them, in the style
of ``scipy.optimize.minimize``.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from has_control.common.errors import shown
from has_control.tuning.restarts import METHOD as RESTARTS, RestartSettings, Restarts
from has_control.tuning.optimiser import OptimiseResult, SwarmError, drive
from has_control.tuning.swarm import VARIANTS, Swarm, SwarmSettings

DEFAULT = RESTARTS
#: Method name -> one line about it (the choices of ``--variant`` and ``swarm.variant``).
METHODS = {RESTARTS: "restarted small-population CMA-ES side by side, then a local polish (default)",
           "pso": "the paper's particle swarm",
           "pso-cp": "the paper's PSO with crazy particles",
           "pso-cp-tvac": "the paper's PSO with crazy particles and time-varying acceleration (the paper's choice)"}


def is_swarm(method: str) -> bool:
    return method in VARIANTS


def check_method(method) -> str:
    if method not in METHODS:
        raise SwarmError(f"swarm.variant = {shown(method)}: expected one of {', '.join(METHODS)}", key="variant")
    return method


def new_optimiser(method: str, bounds, swarm: SwarmSettings | None = None,
                  restarts: RestartSettings | None = None, seed: int | None = None):
    """A fresh optimiser of ``method`` over the box ``bounds``."""
    check_method(method)
    if is_swarm(method):
        return Swarm(bounds, dataclasses.replace(swarm or SwarmSettings(), variant=method), seed)
    return Restarts(bounds, restarts, seed)


def restore(state: dict):
    """The optimiser a ``state_dict`` describes (with its history for ``cma-restarts``)."""
    if state.get("method") == RESTARTS:
        return Restarts.from_state(state)
    return Swarm.from_state(state)


def minimize(objective: Callable[[np.ndarray], np.ndarray], bounds, method: str = DEFAULT,
             seed: int | None = None, callback=None, optimiser=None, **options) -> OptimiseResult:
    """Minimise ``objective`` ((P, M) candidates -> P costs) over ``bounds =
    (lower, upper)`` with ``method``; ``options`` are the method's settings
    (:class:`RestartSettings` or :class:`SwarmSettings` fields, e.g.
    ``particles``, ``iterations``, ``evaluations``). ``callback(optimiser)``
    runs after each batch; returning True stops. ``optimiser`` continues a
    restored one (:func:`restore`; its own settings and bounds then apply)."""
    if optimiser is None:
        try:
            if is_swarm(check_method(method)):
                optimiser = new_optimiser(method, bounds, swarm=SwarmSettings(**options), seed=seed)
            else:
                optimiser = new_optimiser(method, bounds, restarts=RestartSettings(**options), seed=seed)
        except TypeError as exc:
            raise SwarmError(f"minimize: {exc}") from None
    return drive(optimiser, objective, callback)


__all__ = ["METHODS", "DEFAULT", "new_optimiser", "restore", "drive", "minimize", "is_swarm", "check_method"]
