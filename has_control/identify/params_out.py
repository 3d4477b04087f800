"""The identified plant as a ``--params-file``: for the controller's model
(``actuator.*``), the simulated plant (``plant.*``) and the adaptation
(``adaptation.*``: initial estimates and projection bounds consistent with
the identified damping and leakage)."""
from __future__ import annotations

import math

from has_control.config import build_config, flatten, load_yaml
from has_control.core.params import PLANT_OVERRIDES, Config
from has_control.identify.fit import IdentificationResult, identified_config
from has_control.identify.parameters import PARAMETERS


#: The adaptation's bounds around an identified value: at least this factor
#: either side, and never inside the value's 95 % interval.
ADAPTATION_MARGIN = 0.2
#: The plant's structure options, written whole so the file sets the identified structure.
STRUCTURE_FIELDS = (("valve_time_constant", "s"), ("valve_frequency", "Hz"), ("valve_damping_ratio", "-"),
                    ("delay", "samples"), ("friction_coulomb", "N"), ("friction_stribeck", "N"))
#: The adapted parameters (â1, â2) and the plant keys they estimate.
ADAPTED = ("damping", "leakage")


def adaptation_bounds(cfg: Config, result: IdentificationResult) -> tuple | None:
    """(initial, lower, upper) of â = (â1, â2) ≈ (Bp, Ci) consistent with
    the identified plant: â(0) at the identified value (the configured one
    where not estimated), bounds the wider of ±ADAPTATION_MARGIN and the 95 %
    interval; None when neither was estimated."""
    if not any(k in result.estimates for k in ADAPTED):
        return None
    ad = cfg.adaptation
    init, lo, hi = list(ad.initial), list(ad.lower), list(ad.upper)
    for i, k in enumerate(ADAPTED):
        e = result.estimates.get(k)
        if e is None:
            continue
        v = float(e.value)
        init[i] = v
        lo[i] = min(v * (1.0 - ADAPTATION_MARGIN), e.lower if math.isfinite(e.lower) else v)
        hi[i] = max(v * (1.0 + ADAPTATION_MARGIN), e.upper if math.isfinite(e.upper) else v)
        lo[i] = max(lo[i], 0.0)
    return tuple(init), tuple(lo), tuple(hi)


def excluded_by_adaptation(cfg: Config, result: IdentificationResult) -> list[str]:
    """One line for each identified (Bp, Ci) outside the configuration's own
    adaptation bounds (which the params file replaces)."""
    ad = cfg.adaptation
    out = []
    for i, k in enumerate(ADAPTED):
        e = result.estimates.get(k)
        if e is not None and not ad.lower[i] <= e.value <= ad.upper[i]:
            out.append(f"the configuration's adaptation bounds [{ad.lower[i]:g}, {ad.upper[i]:g}] exclude the "
                       f"identified {k} {e.value:.6g}: the params file sets adaptation.* around it")
    return out


def params_yaml(cfg: Config, result: IdentificationResult, note: str = "") -> str:
    """``/**: ros__parameters:`` setting each estimated parameter (a not
    identifiable one at its prior) as ``actuator.<key>`` (the controller's
    model; with ``actuator.area_gradient`` W = G·√ρ/(√2·Cd), so the valve gain
    agrees with Cd, W and ρ as the config requires) and as ``plant.<key>``
    (τ_v only there: the model has no valve lag). Checked by loading it."""
    plant = identified_config(cfg, result).plant
    lines = [f"# {note}"] if note else []
    if result.verdict is not None:
        lines.append(f"# {result.verdict.line()}")
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
    adapt = adaptation_bounds(cfg, result)
    if adapt is not None:
        lines.append("    adaptation:                  # a_hat = (Bp, Ci) around the identified values")
        for name, pair in zip(("initial", "lower", "upper"), adapt):
            lines.append(f"      {name}: [{float(pair[0])!r}, {float(pair[1])!r}]")
    lines.append("    plant:")
    for k in result.estimates:
        lines.append(f"      {k}: {float(getattr(plant, k))!r}   # [{PARAMETERS[k].unit}]")
    for k, unit in STRUCTURE_FIELDS:              # the identified structure, whole
        if k not in result.estimates:
            v = getattr(plant, k)
            lines.append(f"      {k}: {v!r}   # [{unit}] (the structure)" if isinstance(v, int) else
                         f"      {k}: {float(v)!r}   # [{unit}] (the structure)")
    if result.verdict is not None:
        lines.append(f"      model_adequacy: {'adequate' if result.verdict.adequate else 'inadequate'}"
                     "   # identify's verdict (tune vouches for nothing under an inadequate model)")
    if result.verdict is not None and math.isfinite(result.verdict.band_hz) and result.verdict.band_hz > 0.0:
        band = float(result.verdict.band_hz)
        lines.append(f"      validated_band: {band!r}   # [Hz] (tune vouches for its gains above it)")
    text = "\n".join(lines) + "\n"
    build_config(flatten(load_yaml(text, "identified parameters")["/**"]["ros__parameters"]),
                 source="identified parameters", base=cfg)
    return text
