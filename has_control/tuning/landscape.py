"""The tuning objective over 2-D slices of the gain space through a point
(design exploration): where its minima are, and where the bound of the box cuts.

A slice varies two gains over a grid, from the box's lower bound to its upper
bound extended by ``beyond`` (a fraction of the range, so that the cost past
the bound shows; the bound itself is a grid value), the third gain held at the
point's value. Every slice's grid
goes to the objective in one batch. Local minima are the grid points lower
than their (up to) eight neighbours.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from has_control.common.errors import HasControlError
from has_control.common.json_numbers import list_to_json
from has_control.config import GAIN_MAX

PAIRS = ((0, 1), (0, 2), (1, 2))
NAMES = ("k1", "k2", "k3")
#: The most episodes one landscape may plan (slices x points² x scenarios): 3 x 300² nominal, about
#: 20 min on one core; checked before any grid is allocated.
MAX_EPISODES = 270_000


def planned_episodes(points: int, scenarios: int = 0, pairs: int = len(PAIRS)) -> int:
    """The episodes a landscape plans: ``pairs`` slices of ``points``² gain sets, each
    scored on every one of ``scenarios`` (0: the nominal model, one episode)."""
    return pairs * points * points * max(1, scenarios)


def check_plan(points: int, scenarios: int = 0, pairs: int = len(PAIRS)) -> int:
    """:func:`planned_episodes` if at most :data:`MAX_EPISODES`, else an error
    naming the product and the limit (before any allocation)."""
    n = planned_episodes(points, scenarios, pairs)
    if n > MAX_EPISODES:
        over = f" x {scenarios:,} scenarios" if scenarios else ""
        raise HasControlError(f"--points {points}: {pairs} slices x {points}² points{over} = {n:,} episodes, "
                              f"above the limit of {MAX_EPISODES:,} per landscape: fewer points or scenarios")
    return n


@dataclass(frozen=True)
class Slice:
    """J over a grid of gains ``axes`` (i, j) [1/s], the other held at ``point``."""

    axes: tuple[int, int]
    point: tuple[float, float, float]
    xi: np.ndarray              # (n,) values of gain i [1/s]
    xj: np.ndarray              # (n,) values of gain j [1/s]
    J: np.ndarray               # (n, n): J[a, b] at gain i = xi[a], gain j = xj[b]
    lower: tuple[float, float]  # the box on these two gains [1/s]
    upper: tuple[float, float]

    def minima(self) -> list[tuple[float, float, float]]:
        """Local minima of the grid: (gain i, gain j, J), best first."""
        J = np.where(np.isfinite(self.J), self.J, np.inf)
        pad = np.pad(J, 1, constant_values=np.inf)
        n, m = J.shape
        neighbours = [pad[1 + da:1 + da + n, 1 + db:1 + db + m]
                      for da in (-1, 0, 1) for db in (-1, 0, 1) if da or db]
        low = np.isfinite(J) & np.all([J < q for q in neighbours], axis=0)
        out = [(float(self.xi[a]), float(self.xj[b]), float(J[a, b])) for a, b in zip(*np.nonzero(low))]
        return sorted(out, key=lambda p: p[2])

    def best(self) -> tuple[float, float, float]:
        """The grid's lowest J: (gain i, gain j, J)."""
        a, b = np.unravel_index(np.argmin(np.where(np.isfinite(self.J), self.J, np.inf)), self.J.shape)
        return float(self.xi[a]), float(self.xj[b]), float(self.J[a, b])

    def best_inside(self) -> tuple[float, float, float]:
        """The lowest J within the box."""
        inside = ((self.xi[:, None] <= self.upper[0]) & (self.xj[None, :] <= self.upper[1])
                  & (self.xi[:, None] >= self.lower[0]) & (self.xj[None, :] >= self.lower[1]))
        J = np.where(inside & np.isfinite(self.J), self.J, np.inf)
        a, b = np.unravel_index(np.argmin(J), J.shape)
        return float(self.xi[a]), float(self.xj[b]), float(J[a, b])

    def label(self) -> str:
        i, j = self.axes
        k = 3 - i - j
        return f"{NAMES[i]}-{NAMES[j]} at {NAMES[k]} = {self.point[k]:g}"

    def as_json(self) -> dict:
        i, j = self.axes
        return {"gains": [NAMES[i], NAMES[j]], "point": list(self.point), "lower": list(self.lower),
                "upper": list(self.upper), "x": self.xi.tolist(), "y": self.xj.tolist(),
                "J": [list_to_json(row) for row in self.J],
                "best": list_to_json(self.best()), "best_in_box": list_to_json(self.best_inside()),
                "minima": [list_to_json(m) for m in self.minima()]}


def slices(objective: Callable[[np.ndarray], np.ndarray], point: Sequence[float], lower: Sequence[float],
           upper: Sequence[float], points: int = 40, beyond: float = 0.25,
           pairs: Sequence[tuple[int, int]] = PAIRS, scenarios: int = 0) -> list[Slice]:
    """J on a ``points`` x ``points`` grid per pair of gains through ``point``,
    from ``lower`` to ``upper`` + ``beyond`` x range (at most 1e6 1/s); one
    batch call of ``objective`` ((P, 3) gains -> P costs) for all of them.
    ``scenarios``: how many episodes the objective runs per gain set, for the
    bound :func:`check_plan` (checked here, before the grids exist)."""
    check_plan(points, scenarios, len(pairs))
    p = np.asarray(point, dtype=np.float64)
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    top = np.minimum(hi + beyond * (hi - lo), GAIN_MAX)
    grids, blocks = [], []
    for i, j in pairs:
        xi, xj = _axis(lo[i], hi[i], top[i], points), _axis(lo[j], hi[j], top[j], points)
        k = np.repeat(p[None, :], points * points, axis=0)
        k[:, i] = np.repeat(xi, points)
        k[:, j] = np.tile(xj, points)
        grids.append((i, j, xi, xj))
        blocks.append(k)
    costs = np.asarray(objective(np.vstack(blocks)), dtype=np.float64)
    out = []
    for n, (i, j, xi, xj) in enumerate(grids):
        J = costs[n * points * points:(n + 1) * points * points].reshape(points, points)
        J = np.where(np.isnan(J), math.inf, J)
        out.append(Slice((i, j), tuple(float(v) for v in p), xi, xj, J, (float(lo[i]), float(lo[j])),
                         (float(hi[i]), float(hi[j]))))
    return out


def _axis(lo: float, hi: float, top: float, points: int) -> np.ndarray:
    """``points`` equally spaced values from ``lo`` to about ``top``, the bound ``hi`` one of them."""
    steps = max(1, round((points - 1) * (hi - lo) / (top - lo)))
    x = lo + (hi - lo) / steps * np.arange(points)
    x[steps] = hi
    return np.minimum(x, GAIN_MAX)


__all__ = ["Slice", "slices", "PAIRS", "MAX_EPISODES", "check_plan", "planned_episodes"]
