"""The identified plant as a ``--params-file``: for the controller's model
(``actuator.*``) and the simulated plant (``plant.*``)."""
from __future__ import annotations

import math
from pathlib import Path

from has_control.common.files import write_atomic
from has_control.config import build_config, flatten, load_yaml
from has_control.core.params import PLANT_OVERRIDES, Config
from has_control.identify.fit import IdentificationResult, identified_config
from has_control.identify.parameters import PARAMETERS


def params_yaml(cfg: Config, result: IdentificationResult, note: str = "") -> str:
    """``/**: ros__parameters:`` setting each estimated parameter (a not
    identifiable one at its prior) as ``actuator.<key>`` (the controller's
    model; with ``actuator.area_gradient`` W = G·√ρ/(√2·Cd), so the valve gain
    agrees with Cd, W and ρ as the config requires) and as ``plant.<key>``
    (τ_v only there: the model has no valve lag). Checked by loading it."""
    plant = identified_config(cfg, result).plant
    lines = [f"# {note}"] if note else []
    for k, e in result.estimates.items():
        ci = "" if not math.isfinite(e.lower) else f", 95 % [{e.lower:.6g}, {e.upper:.6g}]"
        lines.append(f"# {k}: {e.status}{ci}{' (' + e.why + ')' if e.why else ''}")
    lines += ["/**:", "  ros__parameters:"]
    model = [k for k in result.estimates if k in PLANT_OVERRIDES]
    if model:
        lines.append("    actuator:")
        for k in model:
            lines.append(f"      {k}: {float(getattr(plant, k))!r}   # [{PARAMETERS[k].unit}]")
        if "valve_gain" in model:
            a = cfg.actuator
            w = float(plant.valve_gain) * math.sqrt(a.oil_density) / (math.sqrt(2.0) * a.discharge_coefficient)
            lines.append(f"      area_gradient: {w!r}   # W [m], from valve_gain with Cd and rho as given")
    lines.append("    plant:")
    for k in result.estimates:
        lines.append(f"      {k}: {float(getattr(plant, k))!r}   # [{PARAMETERS[k].unit}]")
    text = "\n".join(lines) + "\n"
    build_config(flatten(load_yaml(text, "identified parameters")["/**"]["ros__parameters"]),
                 source="identified parameters", base=cfg)
    return text


def write_params(path: str | Path, cfg: Config, result: IdentificationResult, note: str = "") -> Path:
    return write_atomic(path, params_yaml(cfg, result, note))
