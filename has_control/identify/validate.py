"""Validation: the identified plant, in closed loop with the recorded run's
controller and reference (the bag's parameters), simulated by the core and
compared with a recording it was not fitted to.

The cylinder's position integrates, so an open-loop simulation from the
recorded commands drifts with any error; the experiment itself was closed
loop, and replaying it is what the recording tests. Fit per signal is the
NRMSE fit of System Identification practice,
100·(1 − ‖measured − simulated‖ / ‖measured − mean(measured)‖) [%].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from has_control.config import with_horizon
from has_control.core.episode import simulate
from has_control.core.params import Config
from has_control.identify.data import Experiment, IdentificationError
from has_control.identify.fit import CHANNELS, IdentificationResult, identified_config


@dataclass(frozen=True)
class Validation:
    """Fit [%] per signal (y, ydot, P1, P2), and the series compared: t [s],
    measured and simulated (n, 4) states [m, m/s, Pa, Pa]."""

    name: str
    fit: dict[str, float]
    t: np.ndarray
    measured: np.ndarray
    simulated: np.ndarray
    diverged: bool

    def as_json(self) -> dict:
        return {"bag": self.name, "fit_percent": self.fit, "diverged": self.diverged}


def nrmse_fit(measured: np.ndarray, simulated: np.ndarray) -> float:
    """100·(1 − ‖m − s‖/‖m − mean(m)‖) [%]; 100 is a perfect fit, it can be negative."""
    spread = np.linalg.norm(measured - measured.mean())
    if spread == 0.0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(measured - simulated) / spread))


def validate(exp: Experiment, result: IdentificationResult | Config) -> Validation:
    """Simulate ``exp``'s run with the identified plant (``result``, or a Config
    whose plant is the model to test) and compare it with ``exp``'s measurements."""
    cfg = result if isinstance(result, Config) else identified_config(exp.cfg, result)
    n = exp.first + exp.samples
    trace = simulate(with_horizon(cfg, n * cfg.episode.step))
    sim = np.column_stack([trace["y"], trace["ydot"], trace["P1"], trace["P2"]])[exp.first:]
    m = min(len(sim), exp.samples)
    if m < 2:
        raise IdentificationError(f"{exp.name}: the identified model diverged at once in closed loop")
    meas = exp.x[:m]
    keep = np.ones(m, dtype=bool)
    gaps = getattr(exp, "gaps", None)
    if gaps is not None and len(gaps):
        keep[gaps[gaps < m]] = False            # rows recorded without a measurement are not compared
    fit = {c: nrmse_fit(meas[keep, k], sim[:m][keep, k]) for k, c in enumerate(CHANNELS)}
    return Validation(exp.name, fit, exp.t[:m], meas, sim[:m], bool(trace.score.diverged))
