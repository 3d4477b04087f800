"""A machine's requirements as a tuning objective, beside the paper's J.

The paper's J (SPEC §6) charges the start-up transient to the gains and
rewards commands no valve can follow (near its optimum most of J is λ2·u² of
commands of several millimetres, at the first samples). A real machine states
requirements instead, as Simulink Design Optimization's response optimisation
takes them: a spool travel the command should stay within, a bound on the
tracking error, on the chamber pressures, on the command's content above a
frequency. Given ``--requirements FILE`` (``requirements.*`` in
``ros__parameters`` form, ``config/requirements_machine.yaml``), a candidate's
cost is

    J_req = J_w · (1 + penalty · Σ_i v_i),   v_i = max(0, g_i / c_i − 1)

with J_w the paper's J over the metric window (``window: true``) or over the
whole run, g_i each measured quantity (:mod:`has_control.core.measures`) and
c_i its limit (a lower bound, ``pressure_min``: v = max(0, 1 − p_min / c)). A
limit of 0 is off. A requirement is *active* at the answer when it is within
5 % of its limit or broken, as an optimiser's active constraints: the tuned
gains would move without it. Without the file J is the paper's, bit for bit.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from has_control.common.errors import ConfigError, shown
from has_control.config import read_parameter_files
from has_control.core.measures import HF_CORNER, MEASURES

#: Each requirement: (its measure, upper or lower bound, unit, text).
REQUIREMENTS = {
    "at_stop": ("at_stop", "upper", "-", "share of the samples with the spool at its travel"),
    "e_max": ("e_max", "upper", "m", "largest |e1| over the metric window"),
    "pressure_min": ("p_min", "lower", "Pa", "lowest chamber pressure"),
    "pressure_max": ("p_max", "upper", "Pa", "highest chamber pressure"),
    "hf_rms": ("hf_rms", "upper", "m", "RMS of the command above hf_frequency"),
}
#: A requirement within this share of its limit is active.
ACTIVE = 0.05
_COLUMNS = ("J", "e_max", "e_mu", "e_sigma") + MEASURES


@dataclass(frozen=True)
class Requirements:
    """``requirements.*``: window (bool) J over the metric window only;
    at_stop [-], e_max [m], pressure_min and pressure_max [Pa], hf_rms [m]
    limits (0: off); hf_frequency [Hz] the corner of hf_rms; penalty [-] the
    weight of a relative violation."""

    window: bool = True
    at_stop: float = 0.01
    e_max: float = 0.0
    pressure_min: float = 0.0
    pressure_max: float = 0.0
    hf_rms: float = 0.0
    hf_frequency: float = HF_CORNER
    penalty: float = 10.0

    def validate(self, where: str = "requirements") -> "Requirements":
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "window":
                if not isinstance(v, bool):
                    raise ConfigError(f"{where}: requirements.window = {shown(v)}: expected true or false")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"{where}: requirements.{f.name} = {shown(v)}: expected a finite number")
            positive = f.name in ("hf_frequency", "penalty")
            if (v <= 0.0) if positive else (v < 0.0):
                raise ConfigError(f"{where}: requirements.{f.name} = {shown(v)}: must be "
                                  + ("> 0" if positive else ">= 0 (0: off)"))
        if self.pressure_max and self.pressure_min >= self.pressure_max:
            raise ConfigError(f"{where}: requirements.pressure_min = {self.pressure_min:g} must be below "
                              f"pressure_max = {self.pressure_max:g}")
        return self

    def limits(self) -> dict[str, float]:
        """The requirements that are on, by name: their limits."""
        return {k: float(getattr(self, k)) for k in REQUIREMENTS if getattr(self, k) > 0.0}

    def tracking(self, runs: np.ndarray) -> np.ndarray:
        """J_w of each run (J over the metric window, or over the whole run):
        the requirements' J before any penalty, as the vouch compares it."""
        return runs[..., _COLUMNS.index("J_window" if self.window else "J")]

    def cost(self, runs: np.ndarray) -> np.ndarray:
        """J_req of each run: ``runs`` (..., 4 + len(MEASURES)) as
        :func:`~has_control.core.episode.evaluate_measured` gives them."""
        col = {c: runs[..., i] for i, c in enumerate(_COLUMNS)}
        base = self.tracking(runs)
        violation = np.zeros_like(base)
        for name, limit in self.limits().items():
            measure, side, _, _ = REQUIREMENTS[name]
            g = col[measure]
            v = 1.0 - g / limit if side == "lower" else g / limit - 1.0
            violation += np.where(np.isfinite(g), np.maximum(v, 0.0), np.inf)
        with np.errstate(invalid="ignore"):
            out = base * (1.0 + self.penalty * violation)
        return np.where(np.isfinite(out), out, np.inf)

    def report(self, run: np.ndarray) -> list[dict]:
        """Each requirement that is on, at one run (a row of ``runs``): value, limit, met, active."""
        col = {c: float(run[i]) for i, c in enumerate(_COLUMNS)}
        rows = []
        for name, limit in self.limits().items():
            measure, side, unit, text = REQUIREMENTS[name]
            g = col[measure]
            met = g >= limit if side == "lower" else g <= limit
            near = g <= limit * (1.0 + ACTIVE) if side == "lower" else g >= limit * (1.0 - ACTIVE)
            rows.append({"requirement": name, "text": text, "unit": unit, "limit": limit, "value": g,
                         "met": bool(met), "active": bool(near or not met)})
        return rows

    def as_json(self) -> dict:
        return dataclasses.asdict(self)


def report_lines(rows: list[dict]) -> list[str]:
    """One line a requirement: ``requirement e_max: 1.2e-3 m <= 2e-3 m (met, active)``."""
    out = []
    for r in rows:
        rel = ">=" if REQUIREMENTS[r["requirement"]][1] == "lower" else "<="
        state = ("met" if r["met"] else "BROKEN") + (", active" if r["active"] else "")
        out.append(f"requirement {r['requirement']} ({r['text']}): {r['value']:.4g} {r['unit']} {rel} "
                   f"{r['limit']:.4g} {r['unit']} ({state})")
    return out


def requirements_from_parameters(flat: Mapping[str, Any], sources: Mapping[str, str] | None = None
                                 ) -> Requirements | None:
    """The ``requirements.*`` of flat parameters (None when there are none)."""
    keys = {k: v for k, v in flat.items() if k.startswith("requirements.")}
    if not keys:
        return None
    known = {f.name for f in dataclasses.fields(Requirements)}
    changes = {}
    for key, value in keys.items():
        name = key[len("requirements."):]
        if name not in known:
            where = (sources or {}).get(key, "requirements")
            raise ConfigError(f"{where}: {key}: unknown requirement (one of {', '.join(sorted(known))})")
        changes[name] = value
    where = ", ".join(sorted({(sources or {}).get(k, "requirements") for k in keys}))
    return Requirements(**changes).validate(where)


def load_requirements(path: str | Path) -> Requirements:
    """The requirements of a ``ros__parameters`` file (``--requirements FILE``)."""
    flat, sources = read_parameter_files([Path(path)])
    req = requirements_from_parameters(flat, sources)
    if req is None:
        raise ConfigError(f"{path}: no requirements.* parameters")
    others = sorted(k for k in flat if not k.startswith("requirements."))
    if others:
        raise ConfigError(f"{path}: {others[0]}: a requirements file sets only requirements.*")
    return req


def requirements_from_json(d: Any, where: str) -> Requirements:
    """A stored Requirements (a session's settings)."""
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected an object of requirements")
    return requirements_from_parameters({f"requirements.{k}": v for k, v in d.items()},
                                        {f"requirements.{k}": where for k in d})
