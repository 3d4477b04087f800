"""The plant parameters identification may estimate: names, units, the
model's value (the prior), default bounds, and where each sits in the plant
array (:meth:`has_control.core.params.Plant.as_array`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import math

from has_control.core.params import (
    BULK, DAMPING, DELAY, FRICTION_COULOMB, FRICTION_STRIBECK, LEAKAGE, MASS, P_SUPPLY, STRUCTURE, STRUCTURE_FULL,
    STRUCTURE_REFERENCE, STRUCTURE_SPOOL, SUBSTEPS, VALVE_GAIN, VALVE_OMEGA, VALVE_RATE, VALVE_ZETA, Config,
)


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
    Parameter("valve_frequency", "Hz", "f_n", VALVE_OMEGA, 10.0, 2000.0, absolute=True),
    Parameter("valve_damping_ratio", "-", "zeta", VALVE_ZETA, 0.1, 3.0, absolute=True),
    Parameter("friction_coulomb", "N", "Fc", FRICTION_COULOMB, 0.0, 5000.0, absolute=True),
)}
#: Parameters of the structure options (a second-order spool, friction): their prior is the
#: configured plant's value, where a candidate structure sets its start.
STRUCTURE_KEYS = ("valve_frequency", "valve_damping_ratio", "friction_coulomb")

#: What ``identify`` estimates unless told: the physically uncertain ones.
DEFAULT_KEYS = ("mass", "damping", "bulk_modulus", "leakage", "valve_gain", "valve_time_constant")

#: A valve lag below this is not told apart from an ideal valve [s] (the scale of τ_v).
TAU_SCALE = 1e-3


def prior(cfg: Config, key: str) -> float:
    """The value identification starts from and falls back to: the controller's
    model ``actuator.<key>`` (for τ_v an ideal valve, 0; for the structure
    options the configured plant's, friction none)."""
    if key in STRUCTURE_KEYS:
        return 0.0 if key == "friction_coulomb" else float(getattr(cfg.plant, key))
    return 0.0 if key == "valve_time_constant" else float(getattr(cfg.actuator, key))


def given(cfg: Config, key: str) -> float:
    """A parameter not estimated: the configured plant's (``plant.<key>``, else ``actuator.<key>``)."""
    if key == "valve_time_constant" or key in STRUCTURE_KEYS:
        return float(getattr(cfg.plant, key))
    return float(getattr(cfg.plant.actuator(cfg.actuator), key))


def scale(key: str, value: float) -> float:
    """The solver's unit for ``key`` around ``value`` (never 0)."""
    if key == "valve_time_constant":
        return TAU_SCALE
    if key == "friction_coulomb":
        return 100.0
    return abs(value) if value != 0.0 else 1.0


def default_bounds(key: str, start: float) -> tuple[float, float]:
    p = PARAMETERS[key]
    if p.absolute:
        return p.lower, p.upper
    return p.lower * start, p.upper * start


def plant_array(base: np.ndarray, keys, values) -> np.ndarray:
    """``base`` (a plant array) with each of ``keys`` set to its value (τ_v as
    its rate 1/τ_v, f_n as ω_n = 2π·f_n, Fc as a friction without a Stribeck
    peak, Fs = Fc), its structure the simplest that holds it."""
    pp = base.copy()
    for k, v in zip(keys, values):
        if k == "valve_time_constant":
            pp[VALVE_RATE] = 1.0 / v if v > 0.0 else 0.0
        elif k == "valve_frequency":
            pp[VALVE_OMEGA] = 2.0 * math.pi * v
        elif k == "friction_coulomb":
            pp[FRICTION_COULOMB] = pp[FRICTION_STRIBECK] = v
        else:
            pp[PARAMETERS[k].slot] = v
    if pp[FRICTION_COULOMB] != 0.0 or pp[FRICTION_STRIBECK] != 0.0 or pp[SUBSTEPS] != 1.0:
        pp[STRUCTURE] = STRUCTURE_FULL
    elif pp[VALVE_OMEGA] > 0.0 or pp[DELAY] != 0.0:
        pp[STRUCTURE] = STRUCTURE_SPOOL
    else:
        pp[STRUCTURE] = STRUCTURE_REFERENCE
    return pp
