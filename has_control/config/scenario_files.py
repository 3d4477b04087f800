"""Scenario files: named overrides of the world, and seeded draws within ranges.

A scenario is a named set of overrides of the world the controller meets
(``plant.*``, ``noise.*``, ``reference.*``: the plant, its sensors, the road),
never of the controller itself. A scenario file lists named scenarios and/or
a seeded random draw of N of them within stated ranges::

    scenarios:                       # named: each a mapping of overrides
      nominal: {}
      heavy: {plant.mass: 1800.0}
      road-D: {reference: {kind: road, road_class: D, seed: 1}}
    random:                          # N more, drawn uniformly (integers for seeds)
      count: 20
      seed: 1
      prefix: draw                   # names draw-000, draw-001, ...
      ranges: {plant.mass: [1200.0, 1800.0], noise.seed: [0, 1000000]}
      set: {noise.position: 1.0e-6}  # the same in every draw
      scale: {plant.mass: [0.95, 1.05]}   # a factor of the base plant's own value, uniform

``scale`` draws relative to the configuration the scenarios are loaded over
(``tune --config identified.yaml --scenarios ...``: the identified plant, its
``plant.*`` where set, else the model's ``actuator.*``), so one file serves any
machine (the two friction forces share one factor; a lag is at least one
step); the drawn values are stored as absolute overrides (a session resumes
with the same ones).

The robust cost over a scenario set is :mod:`has_control.core.scenarios`'.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from has_control.common.errors import ConfigError, shown
from has_control.common.files import read_text
from has_control.config.params_file import MAX_CONFIG_BYTES
from has_control.config.schema import SEED_RANGE, build_config, finite_number, is_seed
from has_control.config.yaml_safe import flatten, load_yaml
from has_control.core.params import Config
from has_control.core.reference import check_road_memory

#: What a scenario may set: the world, not the controller.
SCENARIO_PREFIXES = ("plant.", "noise.", "reference.")
#: Scenarios in one set, named and drawn together.
MAX_SCENARIOS = 10_000
_INTEGER_KEYS = ("noise.seed", "reference.seed", "plant.delay", "plant.substeps")


@dataclass(frozen=True)
class Scenario:
    """A named set of overrides (flat dotted keys, see :data:`SCENARIO_PREFIXES`)."""

    name: str
    overrides: tuple[tuple[str, Any], ...] = ()

    def config(self, base: Config, source: str | None = None) -> Config:
        """``base`` with this scenario's overrides (validated as a params file's)."""
        return build_config(dict(self.overrides), source=source or f"scenario {self.name}", base=base)

    def as_json(self) -> dict:
        return {"name": self.name, "overrides": dict(self.overrides)}


def scenarios_from_json(items: Sequence[Mapping], where: str = "scenarios") -> tuple[Scenario, ...]:
    """Scenarios stored as JSON (a session's settings): a list of {name, overrides}; one line naming
    ``where`` if they are anything else. Check them with :func:`check_scenarios`."""
    if not isinstance(items, list):
        raise ConfigError(f"{where}: expected a list of scenarios, not {shown(items)}")
    out = []
    for d in items:
        if (not isinstance(d, Mapping) or set(d) != {"name", "overrides"} or not isinstance(d["name"], str)
                or not isinstance(d["overrides"], Mapping)):
            raise ConfigError(f"{where}: {shown(d)}: expected {{name: NAME, overrides: {{KEY: VALUE, ...}}}}")
        bad = next((k for k, v in d["overrides"].items() if isinstance(v, (dict, Mapping))), None)
        if bad is not None:
            raise ConfigError(f"{where}: scenario {d['name']}: {shown(bad)}: expected a value, not a mapping")
        out.append(Scenario(d["name"], tuple((str(k), v) for k, v in d["overrides"].items())))
    return tuple(out)


def check_scenarios(scenarios: Sequence[Scenario], base: Config, where: str) -> tuple[Scenario, ...]:
    """What every scenario set must be, from a file or a session (one check for
    both): at least one and at most :data:`MAX_SCENARIOS`, names unique, only
    world keys (:data:`SCENARIO_PREFIXES`), each a valid configuration over
    ``base``, their roads within the memory limit. One line naming
    ``where``, the scenario and the key."""
    if not scenarios:
        raise ConfigError(f"{where}: no scenarios")
    if len(scenarios) > MAX_SCENARIOS:
        raise ConfigError(f"{where}: {len(scenarios)} scenarios, more than the limit of {MAX_SCENARIOS:,}")
    names = [s.name for s in scenarios]
    seen: set[str] = set()
    dup = next((n for n in names if n in seen or seen.add(n)), None)
    if dup is not None:
        raise ConfigError(f"{where}: scenario {dup}: named twice")
    for s in scenarios:
        _overrides(dict(s.overrides), where, s.name)
    cfgs = [s.config(base, source=f"{where}: scenario {s.name}") for s in scenarios]
    check_road_memory([(c.reference, c.episode) for c in cfgs], str(where))
    return tuple(scenarios)


def load_scenarios(path: str | Path, base: Config | None = None) -> tuple[Scenario, ...]:
    """The scenarios of a scenario file (named ones first, then the draws),
    each checked against ``base``. Errors name the file, the scenario and the key."""
    path = Path(path)
    doc = load_yaml(read_text(path, MAX_CONFIG_BYTES, ConfigError), str(path))
    if not isinstance(doc, Mapping) or not doc or set(doc) - {"scenarios", "random"}:
        extra = sorted(set(doc) - {"scenarios", "random"}, key=str) if isinstance(doc, Mapping) else []
        raise ConfigError(f"{path}: expected a mapping with 'scenarios' and/or 'random'"
                          + (f", not {', '.join(map(str, extra))}" if extra else ""))
    out: list[Scenario] = []
    named = doc.get("scenarios") or {}
    if not isinstance(named, Mapping):
        raise ConfigError(f"{path}: scenarios: expected a mapping of names to overrides")
    for name, body in named.items():
        if body is not None and not isinstance(body, Mapping):
            raise ConfigError(f"{path}: scenario {name}: expected a mapping of overrides")
        flat = flatten(body or {}, where=f"{path}: scenario {name}")
        out.append(Scenario(str(name), _overrides(flat, path, str(name))))
    if "random" in doc:
        out.extend(_draws(doc["random"], path, base or Config()))
    return check_scenarios(out, base or Config(), str(path))


def _overrides(flat: Mapping[str, Any], path: Path | str, name: str) -> tuple[tuple[str, Any], ...]:
    for key in flat:
        if not str(key).startswith(SCENARIO_PREFIXES):
            raise ConfigError(f"{path}: scenario {name}: {key}: a scenario sets only "
                              f"{', '.join(p + '*' for p in SCENARIO_PREFIXES)} (the world, not the controller)")
    return tuple((str(k), v) for k, v in flat.items())


def base_value(base: Config, key: str) -> float:
    """The value of world key ``plant.<name>`` in ``base``: the plant's own, else the model's."""
    name = key.split(".", 1)[1]
    v = getattr(base.plant, name, None)
    if v is None:
        v = getattr(base.actuator, name, None)
    if v is None or isinstance(v, (bool, str)):
        raise KeyError(key)
    return float(v)


def _draws(spec: Any, path: Path, base: Config | None = None) -> list[Scenario]:
    """``random:``'s N scenarios: each key of ``ranges`` uniform in [low, high]
    (a whole number for a seed), then each of ``scale`` a factor uniform in
    [low, high] of ``base``'s value, in sorted key order, from one generator."""
    where = f"{path}: random"
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: expected a mapping with count, seed and ranges")
    unknown = sorted(set(spec) - {"count", "seed", "prefix", "ranges", "set", "scale"}, key=str)
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}: unknown key (count, seed, prefix, ranges, set, scale)")
    count, seed = spec.get("count"), spec.get("seed", 0)
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_SCENARIOS:
        raise ConfigError(f"{where}.count = {shown(count)}: expected a whole number in 1..{MAX_SCENARIOS}")
    if not is_seed(seed):
        raise ConfigError(f"{where}.seed = {shown(seed)}: expected a whole number in {SEED_RANGE}")
    prefix = spec.get("prefix", "random")
    if not isinstance(prefix, str) or not prefix:
        raise ConfigError(f"{where}.prefix = {shown(prefix)}: expected a name (the draws are PREFIX-000, ...)")
    ranges, fixed, scale = (flatten(spec.get(k) or {}, where=f"{where}.{k}")
                            if isinstance(spec.get(k) or {}, Mapping) else None for k in ("ranges", "set", "scale"))
    if ranges is None or fixed is None or scale is None:
        raise ConfigError(f"{where}: ranges, set and scale are mappings of keys")
    factors = {}
    for key in sorted(scale):
        r = scale[key]
        ok = isinstance(r, (list, tuple)) and len(r) == 2 and all(
            not isinstance(finite_number(v), str) and float(v) >= 0.0 for v in r) and r[0] <= r[1]
        if not ok:
            raise ConfigError(f"{where}.scale.{key} = {shown(r)}: expected [low, high], two factors >= 0, low <= high")
        if key in ranges or key in _INTEGER_KEYS or not str(key).startswith("plant."):
            raise ConfigError(f"{where}.scale.{key}: scales a plant.* number not also in ranges")
        try:
            factors[key] = (base_value(base or Config(), key), float(r[0]), float(r[1]))
        except KeyError:
            raise ConfigError(f"{where}.scale.{key}: not a plant parameter with a number to scale") from None
    _overrides(fixed, path, f"{prefix}-*")
    _overrides(ranges, path, f"{prefix}-*")
    bounds = {}
    for key in sorted(ranges):
        r = ranges[key]
        ok = isinstance(r, (list, tuple)) and len(r) == 2 and all(
            not isinstance(finite_number(v), str) for v in r) and r[0] <= r[1] and math.isfinite(
            float(r[1]) - float(r[0]))
        if not ok:
            raise ConfigError(f"{where}.ranges.{key} = {shown(r)}: expected [low, high], "
                              "two finite numbers, low <= high, high - low finite")
        if key in _INTEGER_KEYS and not all(is_seed(v) for v in r):
            raise ConfigError(f"{where}.ranges.{key} = {shown(r)}: a seed's range is two whole numbers >= 0")
        bounds[key] = r
    rng = np.random.default_rng(seed)
    step = (base or Config()).episode.step
    width = len(str(count - 1))
    out = []
    for i in range(count):
        drawn = dict(fixed)
        for key, (lo, hi) in bounds.items():
            drawn[key] = int(rng.integers(lo, hi, endpoint=True)) if key in _INTEGER_KEYS else float(
                rng.uniform(lo, hi))
        drawn_factor = {}
        for key, (value, lo, hi) in factors.items():
            if key == "plant.friction_stribeck" and "plant.friction_coulomb" in drawn_factor:
                f = drawn_factor["plant.friction_coulomb"]      # one factor: the friction law keeps its shape
            else:
                f = float(rng.uniform(lo, hi))
            drawn_factor[key] = f
            drawn[key] = value * f
            if key == "plant.valve_time_constant" and 0.0 < drawn[key] < step:
                drawn[key] = step                                # the plant takes 0 or at least one step
        out.append(Scenario(f"{prefix}-{i:0{width}d}", tuple(drawn.items())))
    return out


def scenario_configs(cfg: Config, scenarios: Sequence[Scenario]) -> list[Config]:
    return [s.config(cfg) for s in scenarios]
