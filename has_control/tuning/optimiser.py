"""What every tuning method shares, whatever its search: the ask/tell protocol,
the result, the iteration record, the bounds check and :func:`drive`.

A method (:mod:`~has_control.tuning.swarm`'s particle swarms,
:mod:`~has_control.tuning.restarts`' CMA-ES restarts) is an
:class:`Optimiser`; :func:`has_control.tuning.methods.minimize` is the one
plain function over them, in the style of ``scipy.optimize.minimize``, and
returns an :class:`OptimiseResult` (SciPy's ``OptimizeResult`` fields).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from has_control.common.errors import HasControlError
from has_control.common.json_numbers import list_to_json


class Optimiser(Protocol):
    """An ask/tell optimiser: ``ask()`` the (N, M) candidates, ``tell(costs)``
    their N costs, until ``done``; ``best_x``, ``best_f`` the best so far."""

    name: str
    seed: int
    iteration: int
    evaluations: int
    history: list
    stop_reason: str

    @property
    def done(self) -> bool: ...

    @property
    def best_x(self) -> np.ndarray: ...

    @property
    def best_f(self) -> float: ...

    def ask(self) -> np.ndarray: ...

    def tell(self, costs) -> None: ...

    def progress(self) -> float: ...

    def state_dict(self, history: bool = True) -> dict: ...

    def result(self) -> "OptimiseResult": ...


class BestSoFar:
    """What every method answers the same way from its ``stop_reason``, ``gbest_x``
    and ``gbest_f`` (the swarm's names, still read in saved sessions): ``done``,
    ``best_x`` (the best gains so far) and ``best_f`` (their J)."""

    @property
    def done(self) -> bool:
        return self.stop_reason is not None

    @property
    def best_x(self) -> np.ndarray:
        return self.gbest_x

    @property
    def best_f(self) -> float:
        return self.gbest_f


class OptimiserError(HasControlError, ValueError):
    """Invalid method settings or bounds (one line naming the setting); ``key``
    is the setting at fault (``variant``, ``seed``, ``lower``, ...), or
    ``bounds`` when it is the pair of bounds."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key


SwarmError = OptimiserError             # the name before the methods shared this module


def check_bounds(bounds) -> tuple[np.ndarray, np.ndarray]:
    try:
        lo, hi = (np.asarray(b, dtype=np.float64).ravel() for b in bounds)
    except (TypeError, ValueError):
        raise OptimiserError(f"bounds = {bounds!r}: expected (lower, upper) sequences of numbers",
                             key="bounds") from None
    if lo.shape != hi.shape or lo.size == 0:
        raise OptimiserError(f"bounds: lower {lo.tolist()} and upper {hi.tolist()} differ in length", key="bounds")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise OptimiserError(f"bounds: lower {lo.tolist()} / upper {hi.tolist()} must be finite", key="bounds")
    if np.any(lo >= hi):
        i = int(np.argmax(lo >= hi))
        raise OptimiserError(f"bounds[{i}]: lower {lo[i]:g} must be below upper {hi[i]:g}", key="bounds")
    return lo, hi


@dataclass
class IterationRecord:
    """What one iteration saw: for convergence plots (paper Figs. 3–6)."""

    iteration: int
    best_cost: float
    best_position: np.ndarray
    mean_cost: float
    std_cost: float
    positions: np.ndarray
    costs: np.ndarray


@dataclass
class OptimiseResult:
    """Outcome of a method (like ``scipy.optimize.OptimizeResult``).

    x: best position; fun: its cost; nit: iterations; nfev: evaluations;
    message: why it stopped; success: whether a finite optimum was found;
    nan_costs: how many NaN costs were counted as +inf; history: one
    :class:`IterationRecord` per iteration.
    """

    x: np.ndarray
    fun: float
    nit: int
    nfev: int
    message: str
    success: bool
    nan_costs: int
    history: list[IterationRecord] = field(repr=False, default_factory=list)

    def best_costs(self) -> np.ndarray:
        return np.array([h.best_cost for h in self.history])


SwarmResult = OptimiseResult             # the name before the methods shared this module


def drive(optimiser, objective: Callable[[np.ndarray], np.ndarray],
          callback: Callable[[object], bool | None] | None = None) -> OptimiseResult:
    """Ask, evaluate, tell until ``optimiser`` (any of the ask/tell methods) is
    done; ``callback(optimiser)`` after each batch, True stops."""
    while not optimiser.done:
        optimiser.tell(objective(optimiser.ask()))
        if callback is not None and callback(optimiser):
            optimiser.stop_reason = optimiser.stop_reason or "stopped by callback"
    return optimiser.result()


def _from_json(values) -> list:
    return [float(v) for v in values]


def record_dict(h: IterationRecord) -> dict:
    """An iteration record as JSON-serialisable data (inverse: :func:`record_from`)."""
    return {"iteration": h.iteration, "best_cost": list_to_json([h.best_cost])[0],
            "best_position": h.best_position.tolist(), "mean_cost": list_to_json([h.mean_cost])[0],
            "std_cost": list_to_json([h.std_cost])[0], "positions": h.positions.tolist(),
            "costs": list_to_json(h.costs)}


def record_from(d: dict) -> IterationRecord:
    return IterationRecord(int(d["iteration"]), float(d["best_cost"]), np.array(d["best_position"]),
                           float(d["mean_cost"]), float(d["std_cost"]),
                           np.array(d["positions"], dtype=np.float64).reshape(-1, len(d["best_position"])),
                           np.array(_from_json(d["costs"])))


__all__ = ["Optimiser", "OptimiserError", "OptimiseResult", "IterationRecord", "check_bounds", "drive",
           "record_dict", "record_from", "SwarmError", "SwarmResult"]
