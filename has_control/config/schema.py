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
import re
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from has_control.common.errors import ConfigError, shown
from has_control.config.params_file import read_parameter_files
from has_control.core.params import (
    DELAY_MAX, NOISE_ADDED_BY, ROAD_CLASSES, SUBSTEPS_MAX, VELOCITY_SOURCES, X3D_MODES, REFERENCE_KINDS, Actuator,
    Adaptation, Config, Episode, Gains, Noise, Plant, Reference,
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
    return None if 0 < v <= GAIN_MAX else f"must be > 0 and <= {GAIN_MAX:g}"


def _positive(v: float) -> str | None:
    return None if v > 0 else "must be > 0"


def _non_negative(v: float) -> str | None:
    return None if v >= 0 else "must be >= 0"


def _any(v: float) -> str | None:
    return None


def _int_range(lo: int, hi: int) -> Callable[[int], str | None]:
    def inner(v: int) -> str | None:
        return None if lo <= v <= hi else f"must be a whole number in [{lo}, {hi}]"
    inner.bounds = (lo, hi)
    return inner


def _pair(check: Callable[[float], str | None]) -> Callable[[Any], str | None]:
    def inner(v):
        for x in v:
            msg = check(x)
            if msg:
                return msg
        return None
    return inner


#: A seed: a whole number in [0, SEED_LIMIT).
SEED_LIMIT = 2**63
SEED_RANGE = "[0, 2^63)"             # SEED_LIMIT in words, for error lines


def is_seed(v: Any) -> bool:
    """A whole number (not a bool) in [0, SEED_LIMIT): a seed of the noise, the road or the draws."""
    return isinstance(v, int) and not isinstance(v, bool) and 0 <= v < SEED_LIMIT


# key -> (section attribute, field name, kind, check)
#   kind: "float", "pair" (two floats), "int" (a whole number), "seed" (a whole number in [0, SEED_LIMIT)),
#   or a dict of allowed strings
_SCHEMA: dict[str, tuple[str, str, Any, Callable]] = {}


def _register(prefix: str, section: str, fields: Mapping[str, tuple[Any, Callable]]):
    for name, (kind, check) in fields.items():
        _SCHEMA[f"{prefix}.{name}"] = (section, name, kind, check)


_register("actuator", "actuator", {
    "mass": ("float", _positive), "area_cap": ("float", _positive),
    "area_rod": ("float", _positive), "bulk_modulus": ("float", _positive),
    "damping": ("float", _non_negative), "leakage": ("float", _non_negative),
    "volume_cap0": ("float", _positive), "volume_rod0": ("float", _positive),
    "gravity": ("float", _non_negative), "supply_pressure": ("float", _positive),
    "return_pressure": ("float", _non_negative),
    "discharge_coefficient": ("float", _positive), "area_gradient": ("float", _positive),
    "oil_density": ("float", _positive), "valve_gain": ("float", _positive),
})
_register("gains", "gains", {k: ("float", check_gain) for k in ("k1", "k2", "k3")})
_register("adaptation", "adaptation", {
    "gain": ("pair", _pair(_non_negative)), "initial": ("pair", _pair(_any)),
    "lower": ("pair", _pair(_any)), "upper": ("pair", _pair(_any)),
    "x3d_derivative": (X3D_MODES, None),
})
_register("reference", "reference", {
    "kind": (REFERENCE_KINDS, None), "amplitude": ("float", _any),
    "omega": ("float", _positive), "offset": ("float", _any), "t0": ("float", _non_negative),
    "rise": ("float", _non_negative), "f0": ("float", _non_negative),
    "f1": ("float", _non_negative), "sweep": ("float", _positive),
    "road_class": (ROAD_CLASSES, None), "speed": ("float", _positive), "cutoff": ("float", _positive),
    "seed": ("seed", None),
})
_register("plant", "plant", {
    "mass": ("float", _positive), "bulk_modulus": ("float", _positive),
    "damping": ("float", _non_negative), "leakage": ("float", _non_negative),
    "supply_pressure": ("float", _positive), "valve_gain": ("float", _positive),
    "valve_limit": ("float", _non_negative), "valve_time_constant": ("float", _non_negative),
    "valve_frequency": ("float", _non_negative), "valve_damping_ratio": ("float", _positive),
    "delay": ("int", _int_range(0, DELAY_MAX)), "substeps": ("int", _int_range(1, SUBSTEPS_MAX)),
    "friction_coulomb": ("float", _non_negative), "friction_stribeck": ("float", _non_negative),
    "stribeck_velocity": ("float", _positive), "friction_smoothing": ("float", _positive),
    "validated_band": ("float", _non_negative),
})
_register("noise", "noise", {
    "position": ("float", _non_negative), "velocity": ("float", _non_negative),
    "pressure_cap": ("float", _non_negative), "pressure_rod": ("float", _non_negative),
    "seed": ("seed", None), "added_by": (NOISE_ADDED_BY, None),
    "position_resolution": ("float", _non_negative), "pressure_resolution": ("float", _non_negative),
    "velocity_source": (VELOCITY_SOURCES, None), "velocity_filter_frequency": ("float", _non_negative),
})
_register("simulation", "episode", {
    "step": ("float", _positive), "horizon": ("float", _positive),
    "y_limit": ("float", _positive),
})
_register("cost", "episode", {k: ("float", _non_negative) for k in ("lambda1", "lambda2", "lambda3")})
_register("metrics", "episode", {
    "skip_start": ("float", _non_negative), "skip_end": ("float", _non_negative),
})

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


def _coerce(key: str, value: Any, kind: Any, source: str) -> Any:
    def bad(why: str) -> ConfigError:
        return ConfigError(f"{source}: {key} = {shown(value)}: {why}")

    def number(v: Any) -> float:
        v = finite_number(v)
        if isinstance(v, str):
            raise bad(v)
        return v

    if kind == "float":
        return number(value)
    if kind == "pair":
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise bad("expected a list of two numbers")
        return tuple(number(v) for v in value)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad("expected a whole number")
        return value
    if kind == "seed":
        if not is_seed(value):
            raise bad(f"expected a whole number in {SEED_RANGE}")
        return value
    if isinstance(kind, Mapping):
        if not isinstance(value, str) or value not in kind:
            raise bad(f"expected one of {', '.join(sorted(kind))}")
        return value
    raise AssertionError(kind)


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
        section, attr, kind, check = _SCHEMA[key]
        v = _coerce(key, value, kind, where(key))
        if check is not None:
            msg = check(v)
            if msg:
                raise ConfigError(f"{where(key)}: {key} = {shown(value)}: {msg}")
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
    for key, (section, attr, kind, _) in _SCHEMA.items():
        v = getattr(getattr(cfg, section), attr)
        if v is None:                          # a plant parameter that is the model's
            continue
        out[key] = list(v) if kind == "pair" else v
    return out


def parameter_kind(key: str) -> tuple[Any, tuple[float, bool] | None, float | None]:
    """What a config key takes, for parameter descriptors: its kind ("float",
    "pair" or a dict of allowed strings), its lower bound (value, inclusive)
    and its upper bound (inclusive), where its check has them."""
    _, _, kind, check = _SCHEMA[key]
    lower, upper = {_positive: ((0.0, False), None), _non_negative: ((0.0, True), None),
                    check_gain: ((0.0, False), GAIN_MAX)}.get(check, (None, None))
    if lower is None and kind == "pair":
        lower = {"gain": (0.0, True)}.get(key.rsplit(".", 1)[-1])
    if kind == "seed":
        lower, upper = (0.0, True), SEED_LIMIT - 1
    if kind == "int":
        lo, hi = check.bounds
        lower, upper = (float(lo), True), hi
    return kind, lower, upper


def parameter_comments(files: Iterable[str | Path] | None = None) -> dict[str, str]:
    """The comment after each key in the shipped YAML files (their units and
    meaning), by dotted key, for parameter descriptors."""
    out: dict[str, str] = {}
    for f in files if files is not None else default_config_files():
        stack: list[tuple[int, str, str]] = []          # (indent, section, its comment)
        for line in Path(f).read_text().splitlines():
            m = re.match(r"^(\s*)([A-Za-z_][\w]*):\s*([^#]*?)\s*(?:#\s*(.*))?$", line)
            if not m:
                continue
            indent, key, value, comment = len(m.group(1)), m.group(2), m.group(3), (m.group(4) or "").strip()
            while stack and stack[-1][0] >= indent:
                stack.pop()
            if value:
                dotted = ".".join([k for _, k, _ in stack if k != "ros__parameters"] + [key])
                inherited = next((c for _, _, c in reversed(stack) if c), "")
                if comment or inherited:
                    out[dotted] = comment or inherited
            else:
                stack.append((indent, key, comment))
    return out


def with_horizon(cfg: Config, duration: float | None) -> Config:
    """``cfg`` with its episode horizon set to ``duration`` seconds (None: unchanged)."""
    if duration is None:
        return cfg
    return build_config({"simulation.horizon": float(duration)}, source="--duration", base=cfg)
