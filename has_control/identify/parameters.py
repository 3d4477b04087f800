"""The plant parameters identification may estimate: names, units, the
model's value (the prior), default bounds, and where each sits in the plant
array (:meth:`has_control.core.params.Plant.as_array`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from has_control.core.params import BULK, DAMPING, LEAKAGE, MASS, P_SUPPLY, VALVE_GAIN, VALVE_RATE, Config


@dataclass(frozen=True)
class Parameter:
    """One estimable ``plant.<key>``: unit, scale (a typical size, the unit of
    the solver's variable), default bounds as factors of the prior (or, with
    ``absolute``, in the unit), and its slot in the plant array."""

    key: str
    unit: str
    symbol: str
    slot: int
    lower: float
    upper: float
    absolute: bool = False


#: Every estimable parameter, in table order.
PARAMETERS = {p.key: p for p in (
    Parameter("mass", "kg", "m", MASS, 0.25, 4.0),
    Parameter("damping", "N s/m", "Bp", DAMPING, 0.0, 10.0),
    Parameter("bulk_modulus", "Pa", "beta_e", BULK, 0.25, 4.0),
    Parameter("leakage", "m^3/(s Pa)", "Ci", LEAKAGE, 0.0, 100.0),
    Parameter("valve_gain", "m^2*sqrt(m/kg)", "G", VALVE_GAIN, 0.25, 4.0),
    Parameter("valve_time_constant", "s", "tau_v", VALVE_RATE, 0.0, 0.01, absolute=True),
    Parameter("supply_pressure", "Pa", "Ps", P_SUPPLY, 0.5, 1.5),
)}

#: What ``identify`` estimates unless told: the physically uncertain ones.
DEFAULT_KEYS = ("mass", "damping", "bulk_modulus", "leakage", "valve_gain", "valve_time_constant")

#: A valve lag below this is not told apart from an ideal valve [s] (the scale of τ_v).
TAU_SCALE = 1e-3


def prior(cfg: Config, key: str) -> float:
    """The value identification starts from and falls back to: the controller's
    model ``actuator.<key>`` (for τ_v an ideal valve, 0)."""
    return 0.0 if key == "valve_time_constant" else float(getattr(cfg.actuator, key))


def given(cfg: Config, key: str) -> float:
    """A parameter not estimated: the configured plant's (``plant.<key>``, else ``actuator.<key>``)."""
    if key == "valve_time_constant":
        return float(cfg.plant.valve_time_constant)
    return float(getattr(cfg.plant.actuator(cfg.actuator), key))


def scale(key: str, value: float) -> float:
    """The solver's unit for ``key`` around ``value`` (never 0)."""
    if key == "valve_time_constant":
        return TAU_SCALE
    return abs(value) if value != 0.0 else 1.0


def default_bounds(key: str, start: float) -> tuple[float, float]:
    p = PARAMETERS[key]
    if p.absolute:
        return p.lower, p.upper
    return p.lower * start, p.upper * start


def plant_array(base: np.ndarray, keys, values) -> np.ndarray:
    """``base`` (a plant array) with each of ``keys`` set to its value (τ_v as its rate 1/τ_v)."""
    pp = base.copy()
    for k, v in zip(keys, values):
        if k == "valve_time_constant":
            pp[VALVE_RATE] = 1.0 / v if v > 0.0 else 0.0
        else:
            pp[PARAMETERS[k].slot] = v
    return pp
