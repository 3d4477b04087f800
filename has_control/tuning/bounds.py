"""Bound diagnostics of a tuning result: which gains sit on a bound of the
search box, and whether J still falls beyond it.

A gain within ``tolerance`` (a fraction of its range) of a bound is on it.
For each such gain the objective is probed once more, ``step`` (a fraction of
the range) outside the bound (gains are valid up to 1e6 1/s, so the bound of
a tuning box is a choice, not a physical limit), plus once on the bound when
the gain was only near it; all probes go to the objective in one batch. The
outward directional derivative is their difference quotient. When J falls
outward, the answer is the bound's, not the cost's: the warning says so.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable, Sequence

import numpy as np

from has_control.common.json_numbers import to_json
from has_control.config import GAIN_MAX

TOLERANCE = 1e-3        # on the bound: within this fraction of the gain's range
STEP = 0.01             # the outward probe: this fraction of the gain's range


@dataclass(frozen=True)
class BoundCheck:
    """One gain on a bound: J on the bound and one step outside [1/s]."""

    gain: str               # "k1", "k2", "k3"
    side: str               # "lower" | "upper"
    bound: float            # the bound [1/s]
    value: float            # the tuned gain [1/s]
    step: float             # the outward step [1/s] (0: the bound is the gain limit, no probe)
    J_bound: float          # J with the gain on the bound (the others as tuned)
    J_beyond: float         # J one step outside (NaN without a probe)
    slope: float            # outward directional derivative dJ/d|k - bound| [s], NaN without a probe

    @property
    def falls(self) -> bool:
        """J still falls outside the bound."""
        return bool(self.J_beyond < self.J_bound)

    def warning(self) -> str | None:
        if not self.falls:
            return None
        if self.side == "upper":
            return (f"{self.gain} = {self.bound:g} is the upper bound and J still falls beyond it: the cost "
                    "rewards gain without limit on this model; widen the bound, or tune over scenarios with "
                    "valve lag and sensor noise")
        return (f"{self.gain} = {self.bound:g} is the lower bound and J still falls below it: the optimum "
                "lies outside the box; widen the bound")

    def line(self) -> str:
        where = f"{self.gain} = {self.value:.6g} on the {self.side} bound {self.bound:g}"
        if not self.step:
            return f"{where}: the limit of a gain, not probed"
        trend = "falls" if self.falls else "rises"
        return (f"{where}: J {trend} outside it (J {self.J_bound:.6e} -> {self.J_beyond:.6e} "
                f"{self.step:g} 1/s out, dJ/dk {self.slope:+.3e} s outward)")

    def as_json(self) -> dict:
        return {k: (to_json(v) if isinstance(v, float) else v) for k, v in asdict(self).items()} | {
            "falls": self.falls}


@dataclass(frozen=True)
class BoundDiagnostics:
    """The checks of every gain on a bound, and the probes they cost."""

    checks: tuple[BoundCheck, ...] = ()
    evaluations: int = 0
    tolerance: float = TOLERANCE
    step: float = STEP

    @property
    def warnings(self) -> list[str]:
        return [w for w in (c.warning() for c in self.checks) if w]

    def lines(self) -> list[str]:
        """What ``has-control tune`` prints: one line per gain on a bound, or that none is."""
        if not self.checks:
            return ["bounds: no gain on a bound of the box"]
        return [f"bounds: {c.line()}" for c in self.checks] + [f"warning: {w}" for w in self.warnings]

    def as_json(self) -> dict:
        return {"on_bound": [c.as_json() for c in self.checks], "warnings": self.warnings,
                "evaluations": self.evaluations, "tolerance": self.tolerance, "step": self.step}

    @classmethod
    def from_json(cls, d: dict) -> "BoundDiagnostics":
        fields = BoundCheck.__dataclass_fields__
        checks = tuple(BoundCheck(**{k: (float(v) if fields[k].type == "float" else v)
                                     for k, v in c.items() if k in fields}) for c in d.get("on_bound", ()))
        return cls(checks, int(d.get("evaluations", 0)), float(d.get("tolerance", TOLERANCE)),
                   float(d.get("step", STEP)))


def diagnose(objective: Callable[[np.ndarray], np.ndarray], x: Sequence[float], fun: float,
             lower: Sequence[float], upper: Sequence[float], tolerance: float = TOLERANCE,
             step: float = STEP) -> BoundDiagnostics:
    """Bound diagnostics of the result ``x`` (cost ``fun``) in the box
    ``(lower, upper)``; ``objective`` maps (P, M) gains to P costs (the one the
    result was tuned on)."""
    x = np.asarray(x, dtype=np.float64)
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    span = hi - lo
    found = []                       # (gain, side, bound, signed step)
    for i in range(x.size):
        for side, bound, sign in (("lower", lo[i], -1.0), ("upper", hi[i], 1.0)):
            if abs(x[i] - bound) <= tolerance * span[i]:
                room = bound * 0.5 if sign < 0 else GAIN_MAX - bound
                found.append((i, side, bound, sign * min(step * span[i], room)))
    probes, index = [], []
    for i, _, bound, h in found:
        at = x.copy()
        at[i] = bound
        out = at.copy()
        out[i] = bound + h
        index.append((len(probes) if at[i] != x[i] else None, len(probes) + (at[i] != x[i]) if h else None))
        if at[i] != x[i]:
            probes.append(at)
        if h:
            probes.append(out)
    costs = np.asarray(objective(np.array(probes)), dtype=np.float64) if probes else np.empty(0)
    checks = []
    for (i, side, bound, h), (k_at, k_out) in zip(found, index):
        j_at = float(fun) if k_at is None else float(costs[k_at])
        j_out = math.nan if k_out is None else float(costs[k_out])
        slope = float((j_out - j_at) / abs(h)) if h else math.nan
        checks.append(BoundCheck(f"k{i + 1}", side, float(bound), float(x[i]), abs(float(h)), j_at, j_out, slope))
    return BoundDiagnostics(tuple(checks), len(probes), tolerance, step)


__all__ = ["BoundCheck", "BoundDiagnostics", "diagnose", "TOLERANCE", "STEP"]
