"""Load ``config/*.yaml`` (ROS 2 ``ros__parameters`` form) into typed dataclasses.

A parameter file looks like what ``ros2 run ... --ros-args --params-file``
takes::

    /**:
      ros__parameters:
        actuator:
          mass: 1500.0

Nested keys become dotted parameter names (``actuator.mass``), exactly as
rclpy declares them, so the nodes and the library read the same files.
Every value is checked; a bad one raises :class:`ConfigError` whose message is
one line naming the file, the key and the value.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Iterable, Mapping

from has_control.common.errors import ConfigError, shown
from has_control.config.params_file import read_parameter_files
from has_control.config.table import Param
from has_control.core.params import (
    DELAY_MAX, MODEL_ADEQUACY, NOISE_ADDED_BY, ROAD_CLASSES, SUBSTEPS_MAX, VELOCITY_SOURCES, X3D_MODES,
    REFERENCE_KINDS, Actuator, Adaptation, Config, Episode, Gains, Noise, Plant, Reference,
)
from has_control.core.road import road_components


def _config_dir() -> Path:
    """The shipped ``config/``: the source tree's, or ``share/has_control/config``
    of an install prefix (pip or colcon) above the package."""
    here = Path(__file__).resolve().parent.parent      # the package
    candidates = [here.parent / "config"]
    candidates += [p / "share" / "has_control" / "config" for p in here.parents]
    for c in candidates:
        if (c / "actuator.yaml").is_file():
            return c
    return candidates[0]


#: The reference configuration files shipped with the package.
CONFIG_DIR = _config_dir()


#: Limits checked before anything is allocated or parsed.
MAX_SAMPLES = 10_000_000            # samples of one episode: a trace of 12 float64 columns is 960 MB
GAIN_MAX = 1.0e6                    # [1/s]; the nodes' range descriptor on gains.k1..k3 says the same


def check_gain(v: float) -> str | None:
    """The range of a back-stepping gain (config, --gains, tuning bounds)."""
    return _GAIN.check(v)


#: A seed: a whole number in [0, SEED_LIMIT).
SEED_LIMIT = 2**63
SEED_RANGE = "[0, 2^63)"             # SEED_LIMIT in words, for error lines


def is_seed(v: Any) -> bool:
    """A whole number (not a bool) in [0, SEED_LIMIT): a seed of the noise, the road or the draws."""
    return isinstance(v, int) and not isinstance(v, bool) and 0 <= v < SEED_LIMIT


_POS = dict(lower=0.0, lower_open=True)               # > 0
_NONNEG = dict(lower=0.0)                             # >= 0
_GAIN_RANGE = dict(lower=0.0, lower_open=True, upper=GAIN_MAX)


def _double(name: str, unit: str, text: str, **rng) -> Param:
    return Param(name, "double", unit=unit, text=text, **rng)


def _pair(name: str, unit: str, text: str, **rng) -> Param:
    return Param(name, "double[]", unit=unit, text=text, length=2, **rng)


def _choice(name: str, text: str, choices: Mapping[str, Any]) -> Param:
    return Param(name, "str", text=text, choices=tuple(choices))


def _int(name: str, unit: str, text: str, lower: int, upper: int) -> Param:
    return Param(name, "int", unit=unit, text=text, lower=lower, upper=upper)


def _seed(name: str, text: str) -> Param:
    return Param(name, "int", text=text, lower=0, upper=SEED_LIMIT - 1, range_words=f"in {SEED_RANGE}")


_GAIN = _double("k", "1/s", "a back-stepping gain", **_GAIN_RANGE)

#: The episode's configuration: dotted key -> (Config section attribute, field name, its Param).
#: Defaults come from the shipped config/*.yaml (:func:`load_config`), not from here.
_SCHEMA: dict[str, tuple[str, str, Param]] = {}


def _register(prefix: str, section: str, params: Iterable[Param]) -> None:
    for p in params:
        _SCHEMA[f"{prefix}.{p.name}"] = (section, p.name, dataclasses.replace(p, name=f"{prefix}.{p.name}"))


_register("actuator", "actuator", (
    _double("mass", "kg", "m, moving mass", **_POS),
    _double("area_cap", "m^2", "A1, piston area, cap side", **_POS),
    _double("area_rod", "m^2", "A2, piston area, rod side", **_POS),
    _double("bulk_modulus", "Pa", "beta_e, effective bulk modulus", **_POS),
    _double("damping", "N s/m", "Bp, viscous damping", **_NONNEG),
    _double("leakage", "m^3/(s Pa)", "Ci, internal leakage", **_NONNEG),
    _double("volume_cap0", "m^3", "V01, initial cap-side volume", **_POS),
    _double("volume_rod0", "m^3", "V02, initial rod-side volume", **_POS),
    _double("gravity", "m/s^2", "g", **_NONNEG),
    _double("supply_pressure", "Pa", "Ps, supply pressure", **_POS),
    _double("return_pressure", "Pa", "Pr, return pressure", **_NONNEG),
    _double("discharge_coefficient", "-", "Cd, discharge coefficient", **_POS),
    _double("area_gradient", "m", "W, valve area gradient", **_POS),
    _double("oil_density", "kg/m^3", "rho, oil density", **_POS),
    _double("valve_gain", "m^2/(s sqrt(Pa))", "G = sqrt(2) Cd W sqrt(1/rho) ki, ki = 1 (Table 1 value)", **_POS),
))
_register("gains", "gains", (
    _double("k1", "1/s", "back-stepping gain k1 (the paper's manual set)", **_GAIN_RANGE),
    _double("k2", "1/s", "back-stepping gain k2 (the paper's manual set)", **_GAIN_RANGE),
    _double("k3", "1/s", "back-stepping gain k3 (the paper's manual set)", **_GAIN_RANGE),
))
_register("adaptation", "adaptation", (
    _pair("gain", "", 'sigma1, sigma2 (paper prints "10 x 10^-50")', **_NONNEG),
    _pair("initial", "", "a_hat(0) = (Bp, Ci) estimates"),
    _pair("lower", "", "a_min"),
    _pair("upper", "", "a_max"),
    _choice("x3d_derivative", "analytic (reference) | backward_difference", X3D_MODES),
))
_register("reference", "reference", (
    _choice("kind", "zero | sine | step | chirp | road", REFERENCE_KINDS),
    _double("amplitude", "m", "amplitude"),
    _double("omega", "rad/s", "sine angular frequency", **_POS),
    _double("offset", "m", "offset"),
    _double("t0", "s", "step time", **_NONNEG),
    _double("rise", "s", "step rise time (0: hard step)", **_NONNEG),
    _double("f0", "Hz", "chirp start frequency", **_NONNEG),
    _double("f1", "Hz", "chirp end frequency", **_NONNEG),
    _double("sweep", "s", "chirp sweep duration", **_POS),
    _choice("road_class", "road: ISO 8608 class A..E", ROAD_CLASSES),
    _double("speed", "m/s", "road: vehicle speed", **_POS),
    _double("cutoff", "Hz", "road: highest frequency the actuator is asked to follow", **_POS),
    _seed("seed", "road: random phases"),
))
_register("plant", "plant", (
    *(_double(name, unit, f"the plant's own {name} (default: actuator.{name})", **rng) for name, unit, rng in (
        ("mass", "kg", _POS), ("bulk_modulus", "Pa", _POS), ("damping", "N s/m", _NONNEG),
        ("leakage", "m^3/(s Pa)", _NONNEG), ("supply_pressure", "Pa", _POS),
        ("valve_gain", "m^2/(s sqrt(Pa))", _POS))),
    _double("valve_limit", "m", "u_max, spool travel |u| <= u_max (0: no limit)", **_NONNEG),
    _double("valve_time_constant", "s", "tau_v, first-order valve lag (0: ideal valve; else >= simulation.step)",
            **_NONNEG),
    _double("valve_frequency", "Hz", "f_n, second-order spool (0: not second order; excludes valve_time_constant)",
            **_NONNEG),
    _double("valve_damping_ratio", "-", "zeta of the second-order spool", **_POS),
    _int("delay", "samples", "transport delay of the command", 0, DELAY_MAX),
    _double("delay_fraction", "samples", "a further fraction of a sample of delay, the command interpolated "
            "linearly between samples (0: whole samples)", lower=0.0, upper=1.0, upper_open=True),
    _int("substeps", "", "RK4 steps per sample, the command held", 1, SUBSTEPS_MAX),
    _double("friction_coulomb", "N", "Fc, Coulomb friction on the piston (0: none)", **_NONNEG),
    _double("friction_stribeck", "N", "Fs, static (breakaway) friction (0 with Fc = 0: none)", **_NONNEG),
    _double("stribeck_velocity", "m/s", "v_s, Stribeck velocity", **_POS),
    _double("friction_smoothing", "m/s", "eps, the friction's sign is v/sqrt(v^2 + eps^2)", **_POS),
    _double("validated_band", "Hz", "identify's validated band for this plant (0: not stated; tune vouches above it)",
            **_NONNEG),
    _choice("model_adequacy", "identify's verdict on this plant: unstated | adequate | inadequate (tune vouches for "
            "nothing under an inadequate model)", MODEL_ADEQUACY),
))
_register("noise", "noise", (
    _double("position", "m", "standard deviation on y", **_NONNEG),
    _double("velocity", "m/s", "standard deviation on ydot", **_NONNEG),
    _double("pressure_cap", "Pa", "standard deviation on P1", **_NONNEG),
    _double("pressure_rod", "Pa", "standard deviation on P2", **_NONNEG),
    _seed("seed", "the noise is a pure function of (seed, sample, channel)"),
    _choice("added_by", "controller (adds it to the true states it reads) | plant (publishes readings)",
            NOISE_ADDED_BY),
    _double("position_resolution", "m", "readings of y rounded to multiples of this (0: none), after the noise",
            **_NONNEG),
    _double("pressure_resolution", "Pa", "readings of P1, P2 rounded to multiples of this (0: none)", **_NONNEG),
    _choice("velocity_source", "measured (ydot plus its noise) | derived ((y_i - y_i-1)/step of the readings)",
            VELOCITY_SOURCES),
    _double("velocity_filter_frequency", "Hz", "first-order filter of a derived velocity (0: unfiltered)",
            **_NONNEG),
))
_register("simulation", "episode", (
    _double("step", "s", "sampling time and RK4 step", **_POS),
    _double("horizon", "s", "episode length; n = round(horizon/step) samples", **_POS),
    _double("y_limit", "m", "|y| beyond this means the run diverged", **_POS),
))
_register("cost", "episode", (
    _double("lambda1", "", "weight of |e1|", **_NONNEG),
    _double("lambda2", "", "weight of u^2", **_NONNEG),
    _double("lambda3", "", "overshoot penalty on |e1| when e1 < 0", **_NONNEG),
))
_register("metrics", "episode", (
    _double("skip_start", "s", "steady-state window starts here", **_NONNEG),
    _double("skip_end", "s", "... and ends this long before the horizon", **_NONNEG),
))

#: The configuration's table (dotted key -> Param): descriptors, --help and the YAML comments derive from it.
CONFIG_TABLE: dict[str, Param] = {key: p for key, (_, _, p) in _SCHEMA.items()}

#: Keys that belong to the nodes and tools, not to the episode; accepted and
#: passed through (their owners validate them).
_PASSTHROUGH_PREFIXES = ("controller.", "tuner.", "swarm.", "restarts.", "recorder.")
_PASSTHROUGH_KEYS = {"use_sim_time"}


def finite_number(v: Any) -> float | str:
    """``v`` as a finite float, else why not (a string)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return "expected a number"
    try:
        v = float(v)
    except OverflowError:                      # an integer of hundreds of digits
        return "must be finite"
    return v if math.isfinite(v) else "must be finite"


def build_config(flat: Mapping[str, Any], source: str = "parameters",
                 base: Config | None = None, sources: Mapping[str, str] | None = None) -> Config:
    """Validated :class:`Config` from flat dotted parameters over ``base``.

    ``sources`` maps a key to the file it came from, for the error message.
    Unknown keys are errors; keys of the nodes and tools pass through.
    """
    base = base or Config()
    sections = {name: dataclasses.asdict(getattr(base, name)) for name in
                ("actuator", "gains", "adaptation", "reference", "episode", "plant", "noise")}
    where = lambda key: (sources or {}).get(key, source)  # noqa: E731
    for key, value in flat.items():
        if key not in _SCHEMA and (key in _PASSTHROUGH_KEYS or key.startswith(_PASSTHROUGH_PREFIXES)):
            continue
        if key not in _SCHEMA:
            raise ConfigError(f"{where(key)}: {key}: unknown parameter")
        section, attr, param = _SCHEMA[key]
        why = param.check(value)
        if why:
            raise ConfigError(f"{where(key)}: {key} = {shown(value)}: {why}")
        v = param.coerce(value)
        v = tuple(float(x) for x in v) if param.is_array else (float(v) if param.type == "double" else v)
        sections[section][attr] = v
    cfg = Config(
        actuator=Actuator(**sections["actuator"]), gains=Gains(**sections["gains"]),
        adaptation=Adaptation(**sections["adaptation"]),
        reference=Reference(**sections["reference"]), episode=Episode(**sections["episode"]),
        plant=Plant(**sections["plant"]), noise=Noise(**sections["noise"]),
    )
    _check_relations(cfg, flat, where)
    return cfg


def _check_relations(cfg: Config, flat: Mapping[str, Any], where) -> None:
    """Checks that involve more than one key, each blamed on the key that breaks it."""
    a, ad, ep = cfg.actuator, cfg.adaptation, cfg.episode

    def fail(key: str, value: Any, why: str):
        raise ConfigError(f"{where(key)}: {key} = {shown(value)}: {why}")

    if a.supply_pressure <= a.return_pressure:
        fail("actuator.supply_pressure", a.supply_pressure,
             f"must exceed actuator.return_pressure ({a.return_pressure})")
    derived = a.derived_valve_gain()
    if abs(a.valve_gain - derived) > 0.01 * derived:
        fail("actuator.valve_gain", a.valve_gain,
             f"disagrees with sqrt(2)*Cd*W/sqrt(rho) = {derived:.4g} by more than 1 %")
    for i in range(2):
        if ad.lower[i] > ad.upper[i]:
            fail("adaptation.lower", list(ad.lower), f"lower[{i}] exceeds adaptation.upper[{i}] = {ad.upper[i]}")
        if not ad.lower[i] <= ad.initial[i] <= ad.upper[i]:
            fail("adaptation.initial", list(ad.initial), f"initial[{i}] outside [lower, upper]")
    if ep.step >= ep.horizon:
        fail("simulation.step", ep.step, f"must be smaller than simulation.horizon ({ep.horizon})")
    if ep.horizon / ep.step > MAX_SAMPLES:
        key = "simulation.step" if "simulation.step" in flat else "simulation.horizon"
        fail(key, getattr(ep, key.split(".")[1]),
             f"{ep.horizon:g} s in steps of {ep.step:g} s is {ep.horizon / ep.step:.4g} samples, "
             f"more than the limit of {MAX_SAMPLES:,}")
    start, end = ep.window()
    if ep.skip_start + ep.skip_end >= ep.horizon or start > end:
        skips = (f"the metric window leaves out the first {ep.skip_start:g} s (metrics.skip_start) and the last "
                 f"{ep.skip_end:g} s (metrics.skip_end), so no sample is scored")
        key = "metrics.skip_end" if "metrics.skip_end" in flat else "metrics.skip_start"
        fail(key, getattr(ep, key.split(".")[1]), f"{skips} of the {ep.horizon:g} s horizon "
             f"(simulation.horizon; --duration): make the horizon longer than {ep.skip_start + ep.skip_end:g} s "
             "or the skips shorter")
    _check_plant(cfg, fail)


def _check_plant(cfg: Config, fail) -> None:
    """The plant's and the reference's checks that involve other keys."""
    plant, ep, ref = cfg.plant, cfg.episode, cfg.reference
    true = plant.actuator(cfg.actuator)
    if true.supply_pressure <= true.return_pressure:
        key = "plant.supply_pressure" if plant.supply_pressure is not None else "actuator.return_pressure"
        fail(key, getattr(true, key.split(".")[1]),
             f"the plant's supply pressure must exceed its return pressure ({true.return_pressure})")
    if 0.0 < plant.valve_time_constant < ep.step:
        fail("plant.valve_time_constant", plant.valve_time_constant,
             f"must be 0 (an ideal valve) or at least simulation.step ({ep.step:g} s), for the RK4 step")
    if plant.valve_frequency > 0.0:
        if plant.valve_time_constant > 0.0:
            fail("plant.valve_frequency", plant.valve_frequency,
                 "a second-order spool excludes plant.valve_time_constant (set one of them to 0)")
        limit = plant.substeps / (2.0 * math.pi * ep.step)
        if plant.valve_frequency > limit:
            fail("plant.valve_frequency", plant.valve_frequency,
                 f"must be at most substeps/(2*pi*simulation.step) = {limit:.4g} Hz, for the RK4 step")
    if plant.delay_fraction > 0.0 and plant.delay >= DELAY_MAX:
        fail("plant.delay_fraction", plant.delay_fraction,
             f"must be 0 with plant.delay = {DELAY_MAX} (the longest delay the kernels hold)")
    if ref.kind == "road":
        if ref.cutoff >= 0.5 / ep.step:        # first: it bounds the number of components
            fail("reference.cutoff", ref.cutoff, f"must be below the Nyquist frequency {0.5 / ep.step:g} Hz")
        f, _, _ = road_components(ref, ep.samples * ep.step)
        if len(f) == 0:
            fail("reference.cutoff", ref.cutoff,
                 f"no road component between the band's lower edge and the cutoff (at {ref.speed:g} m/s over a "
                 f"{ep.samples * ep.step:g} s period); raise the cutoff or the speed")


def default_config_files() -> list[Path]:
    """The package's own ``config/*.yaml`` that define the episode."""
    return [CONFIG_DIR / name for name in ("actuator.yaml", "controller.yaml", "simulation.yaml", "plant.yaml")]


def load_config(paths: Iterable[str | Path] = (), defaults: bool = True) -> Config:
    """Config from the shipped files (if ``defaults``) overridden by ``paths`` in order."""
    files = (default_config_files() if defaults else []) + [Path(p) for p in paths]
    flat, sources = read_parameter_files(files)
    return build_config(flat, sources=sources)


def config_parameters(cfg: Config) -> dict[str, Any]:
    """The inverse of :func:`build_config`: flat ROS parameters of a Config."""
    out: dict[str, Any] = {}
    for key, (section, attr, param) in _SCHEMA.items():
        v = getattr(getattr(cfg, section), attr)
        if v is None:                          # a plant parameter that is the model's
            continue
        out[key] = list(v) if param.is_array else v
    return out


def with_horizon(cfg: Config, duration: float | None) -> Config:
    """``cfg`` with its episode horizon set to ``duration`` seconds (None: unchanged)."""
    if duration is None:
        return cfg
    return build_config({"simulation.horizon": float(duration)}, source="--duration", base=cfg)
