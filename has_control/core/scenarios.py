"""The robust cost over a set of scenarios.

A scenario (see :mod:`has_control.config.scenario_files`) is anything with a
``name`` and a ``config(base)`` that gives the world it describes.
:func:`evaluate_scenarios` scores gain sets on every scenario and reduces
each row with an :class:`Aggregate`: the mean, the worst case, or the CVaR at
α (the mean of the worst ⌈α·S⌉ of S costs). A diverged run costs +inf, so a
gain set that loses any scenario it is aggregated over is +inf for max and
for a CVaR tail that holds it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import numpy as np

from has_control.common.errors import ConfigError
from has_control.core.params import Config


class Scenario(Protocol):
    """A named world: :class:`has_control.config.scenario_files.Scenario` is one."""

    name: str

    def config(self, base: Config) -> Config:
        """``base`` in this world."""


@dataclass(frozen=True)
class Aggregate:
    """How one gain set's S scenario costs become one: ``mean``, ``max`` (the
    worst case) or ``cvar`` at ``alpha`` (mean of the worst ⌈α·S⌉)."""

    kind: str = "mean"
    alpha: float = 1.0

    def __str__(self) -> str:
        """``mean``, ``max`` or ``cvar:α``; α as short as :func:`parse_aggregate` reads it back exactly
        (a session stores this: a rounded α could change the tail's size ⌈α·S⌉ on resume)."""
        if self.kind != "cvar":
            return self.kind
        short = f"{self.alpha:g}"
        return f"cvar:{short if float(short) == self.alpha else repr(float(self.alpha))}"

    def __call__(self, costs: np.ndarray) -> np.ndarray:
        """(P, S) costs → (P,) aggregates."""
        c = np.asarray(costs, dtype=np.float64)
        if self.kind == "max":
            return c.max(axis=1)
        if self.kind == "mean":
            return _mean(c)
        k = max(1, math.ceil(self.alpha * c.shape[1] - 1e-12))
        return _mean(-np.sort(-c, axis=1)[:, :k])


def _mean(c: np.ndarray) -> np.ndarray:
    """Row means, +inf where a row holds +inf (without numpy's inf − inf warnings)."""
    out = np.full(c.shape[0], math.inf)
    finite = np.all(np.isfinite(c), axis=1)
    out[finite] = c[finite].mean(axis=1)
    return out


def parse_aggregate(text: str) -> Aggregate:
    """``mean``, ``max`` or ``cvar:α`` with 0 < α ≤ 1 (e.g. ``cvar:0.2``)."""
    t = str(text).strip()
    if t in ("mean", "max"):
        return Aggregate(t)
    if t.startswith("cvar:"):
        try:
            alpha = float(t[5:])
        except ValueError:
            alpha = math.nan
        if 0.0 < alpha <= 1.0:
            return Aggregate("cvar", alpha)
    raise ConfigError(f"aggregate {text!r}: expected mean, max or cvar:ALPHA with 0 < ALPHA <= 1")


@dataclass(frozen=True)
class ScenarioScores:
    """P gain sets on S scenarios: ``metrics[p, s]`` = (J, e_max, e_μ, e_σ),
    and each gain set's aggregate J."""

    names: tuple[str, ...]
    metrics: np.ndarray
    aggregate: Aggregate

    @property
    def costs(self) -> np.ndarray:
        """(P, S) J."""
        return self.metrics[:, :, 0]

    @property
    def robust(self) -> np.ndarray:
        """(P,) aggregate J."""
        return self.aggregate(self.costs)


def evaluate_scenarios(gains, cfg: Config, scenarios: Sequence[Scenario], aggregate: Aggregate | str,
                       batch: Callable[[np.ndarray, list], np.ndarray]) -> ScenarioScores:
    """Every gain set (P, 3) on every scenario over ``cfg``, by ``batch``
    (:func:`~has_control.core.episode.evaluate_configs`, which
    ``episode.evaluate(..., scenarios=...)`` passes, or a Dask one: the same bits)."""
    agg = parse_aggregate(aggregate) if isinstance(aggregate, str) else aggregate
    metrics = batch(gains, [s.config(cfg) for s in scenarios])
    return ScenarioScores(tuple(s.name for s in scenarios), metrics, agg)
