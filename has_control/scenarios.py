"""Scenario sets and the robust cost over them.

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

:func:`evaluate_scenarios` scores gain sets on every scenario and reduces
each row with an :class:`Aggregate`: the mean, the worst case, or the CVaR at
α (the mean of the worst ⌈α·S⌉ of S costs). A diverged run costs +inf, so a
gain set that loses any scenario it is aggregated over is +inf for max and
for a CVaR tail that holds it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .config import MAX_CONFIG_BYTES, build_config, finite_number, flatten, is_seed, load_yaml
from .errors import ConfigError, shown
from .files import read_text
from .params import Config

#: What a scenario may set: the world, not the controller.
SCENARIO_PREFIXES = ("plant.", "noise.", "reference.")
#: Scenarios in one set, named and drawn together.
MAX_SCENARIOS = 10_000
_INTEGER_KEYS = ("noise.seed", "reference.seed")


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


def scenarios_from_json(items: Sequence[Mapping]) -> tuple[Scenario, ...]:
    return tuple(Scenario(str(d["name"]), tuple((str(k), v) for k, v in d["overrides"].items())) for d in items)


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
        out.append(Scenario(str(name), _overrides(flatten(body or {}), path, str(name))))
    if "random" in doc:
        out.extend(_draws(doc["random"], path))
    if not out:
        raise ConfigError(f"{path}: no scenarios")
    if len(out) > MAX_SCENARIOS:
        raise ConfigError(f"{path}: {len(out)} scenarios, more than the limit of {MAX_SCENARIOS:,}")
    names = [s.name for s in out]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise ConfigError(f"{path}: scenario {dup}: named twice")
    base = base or Config()
    for s in out:
        s.config(base, source=f"{path}: scenario {s.name}")
    return tuple(out)


def _overrides(flat: Mapping[str, Any], path: Path, name: str) -> tuple[tuple[str, Any], ...]:
    for key in flat:
        if not str(key).startswith(SCENARIO_PREFIXES):
            raise ConfigError(f"{path}: scenario {name}: {key}: a scenario sets only "
                              f"{', '.join(p + '*' for p in SCENARIO_PREFIXES)} (the world, not the controller)")
    return tuple((str(k), v) for k, v in flat.items())


def _draws(spec: Any, path: Path) -> list[Scenario]:
    """``random:``'s N scenarios: each key of ``ranges`` uniform in [low, high]
    (a whole number for a seed), in sorted key order, from one generator."""
    where = f"{path}: random"
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: expected a mapping with count, seed and ranges")
    unknown = sorted(set(spec) - {"count", "seed", "prefix", "ranges", "set"}, key=str)
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}: unknown key (count, seed, prefix, ranges, set)")
    count, seed = spec.get("count"), spec.get("seed", 0)
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_SCENARIOS:
        raise ConfigError(f"{where}.count = {shown(count)}: expected a whole number in 1..{MAX_SCENARIOS}")
    if not is_seed(seed):
        raise ConfigError(f"{where}.seed = {shown(seed)}: expected a whole number in [0, 2^63)")
    prefix = spec.get("prefix", "random")
    if not isinstance(prefix, str) or not prefix:
        raise ConfigError(f"{where}.prefix = {shown(prefix)}: expected a name (the draws are PREFIX-000, ...)")
    ranges = flatten(spec.get("ranges") or {}) if isinstance(spec.get("ranges") or {}, Mapping) else None
    fixed = flatten(spec.get("set") or {}) if isinstance(spec.get("set") or {}, Mapping) else None
    if ranges is None or fixed is None:
        raise ConfigError(f"{where}: ranges and set are mappings of keys")
    _overrides(fixed, path, f"{prefix}-*")
    _overrides(ranges, path, f"{prefix}-*")
    bounds = {}
    for key in sorted(ranges):
        r = ranges[key]
        ok = isinstance(r, (list, tuple)) and len(r) == 2 and all(
            not isinstance(finite_number(v), str) for v in r) and r[0] <= r[1]
        if not ok:
            raise ConfigError(f"{where}.ranges.{key} = {shown(r)}: expected [low, high], "
                              "two finite numbers, low <= high")
        if key in _INTEGER_KEYS and not all(is_seed(v) for v in r):
            raise ConfigError(f"{where}.ranges.{key} = {shown(r)}: a seed's range is two whole numbers >= 0")
        bounds[key] = r
    rng = np.random.default_rng(seed)
    width = len(str(count - 1))
    out = []
    for i in range(count):
        drawn = dict(fixed)
        for key, (lo, hi) in bounds.items():
            drawn[key] = int(rng.integers(lo, hi, endpoint=True)) if key in _INTEGER_KEYS else float(
                rng.uniform(lo, hi))
        out.append(Scenario(f"{prefix}-{i:0{width}d}", tuple(drawn.items())))
    return out


@dataclass(frozen=True)
class Aggregate:
    """How one gain set's S scenario costs become one: ``mean``, ``max`` (the
    worst case) or ``cvar`` at ``alpha`` (mean of the worst ⌈α·S⌉)."""

    kind: str = "mean"
    alpha: float = 1.0

    def __str__(self) -> str:
        """``mean``, ``max`` or ``cvar:α``; α as short as :func:`parse_aggregate` reads it back exactly
        (a session stores this: a rounded α could change the tail's size ⌈α·S⌉ on resume)."""
        if self.kind != "cvar":
            return self.kind
        short = f"{self.alpha:g}"
        return f"cvar:{short if float(short) == self.alpha else repr(float(self.alpha))}"

    def __call__(self, costs: np.ndarray) -> np.ndarray:
        """(P, S) costs → (P,) aggregates."""
        c = np.asarray(costs, dtype=np.float64)
        if self.kind == "max":
            return c.max(axis=1)
        if self.kind == "mean":
            return _mean(c)
        k = max(1, math.ceil(self.alpha * c.shape[1] - 1e-12))
        return _mean(-np.sort(-c, axis=1)[:, :k])


def _mean(c: np.ndarray) -> np.ndarray:
    """Row means, +inf where a row holds +inf (without numpy's inf − inf warnings)."""
    out = np.full(c.shape[0], math.inf)
    finite = np.all(np.isfinite(c), axis=1)
    out[finite] = c[finite].mean(axis=1)
    return out


def parse_aggregate(text: str) -> Aggregate:
    """``mean``, ``max`` or ``cvar:α`` with 0 < α ≤ 1 (e.g. ``cvar:0.2``)."""
    t = str(text).strip()
    if t in ("mean", "max"):
        return Aggregate(t)
    if t.startswith("cvar:"):
        try:
            alpha = float(t[5:])
        except ValueError:
            alpha = math.nan
        if 0.0 < alpha <= 1.0:
            return Aggregate("cvar", alpha)
    raise ConfigError(f"aggregate {text!r}: expected mean, max or cvar:ALPHA with 0 < ALPHA <= 1")


@dataclass(frozen=True)
class ScenarioScores:
    """P gain sets on S scenarios: ``metrics[p, s]`` = (J, e_max, e_μ, e_σ),
    and each gain set's aggregate J."""

    names: tuple[str, ...]
    metrics: np.ndarray
    aggregate: Aggregate

    @property
    def costs(self) -> np.ndarray:
        """(P, S) J."""
        return self.metrics[:, :, 0]

    @property
    def robust(self) -> np.ndarray:
        """(P,) aggregate J."""
        return self.aggregate(self.costs)


def scenario_configs(cfg: Config, scenarios: Sequence[Scenario]) -> list[Config]:
    return [s.config(cfg) for s in scenarios]


def evaluate_scenarios(gains, cfg: Config, scenarios: Sequence[Scenario], aggregate: Aggregate | str,
                       batch: Callable[[np.ndarray, list], np.ndarray]) -> ScenarioScores:
    """Every gain set (P, 3) on every scenario over ``cfg``, by ``batch``
    (:func:`~has_control.episode.evaluate_configs`, which
    ``episode.evaluate(..., scenarios=...)`` passes, or a Dask one: the same bits)."""
    agg = parse_aggregate(aggregate) if isinstance(aggregate, str) else aggregate
    metrics = batch(gains, scenario_configs(cfg, scenarios))
    return ScenarioScores(tuple(s.name for s in scenarios), metrics, agg)
