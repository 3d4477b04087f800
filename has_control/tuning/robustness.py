"""How gain sets hold off the nominal model: J and e_max on every scenario of a set.

``has-control robustness`` prints, writes (Markdown, JSON) and plots a
:class:`RobustnessTable`: one row per scenario, a J and an e_max column per
gain set, and below them each gain set's mean, tail (CVaR) and worst J and
the number of scenarios it lost (diverged).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from has_control.core.episode import evaluate_configs
from has_control.common.errors import ConfigError
from has_control.common.json_numbers import to_json
from has_control.core.params import Config
from has_control.core.scenarios import Aggregate, ScenarioScores, evaluate_scenarios
from has_control.config import Scenario


@dataclass(frozen=True)
class RobustnessTable:
    """Gain sets (``labels``, ``gains``) scored on scenarios (``scores``)."""

    labels: tuple[str, ...]
    gains: tuple[tuple[float, float, float], ...]
    scores: ScenarioScores
    kinds: tuple[str, ...] = ()          # each scenario's kind (:func:`scenario_kind`), for the figure

    def summary(self) -> dict[str, dict[str, float]]:
        """Per label: mean, the tail aggregate, max J, and the scenarios diverged."""
        c = self.scores.costs
        tail = self.scores.aggregate
        rows = {"mean": Aggregate("mean")(c), str(tail): tail(c), "max": Aggregate("max")(c)}
        out = {}
        for p, label in enumerate(self.labels):
            out[label] = {k: float(v[p]) for k, v in rows.items()}
            out[label]["diverged"] = int(np.sum(~np.isfinite(c[p])))
        return out

    def as_json(self) -> dict:
        m = self.scores.metrics
        return {"scenarios": list(self.scores.names), "labels": list(self.labels),
                "gains": [list(g) for g in self.gains],
                "J": [[to_json(v) for v in m[p, :, 0]] for p in range(len(self.labels))],
                "e_max": [[to_json(v) for v in m[p, :, 1]] for p in range(len(self.labels))],
                "summary": {k: {a: to_json(v) for a, v in d.items()} for k, d in self.summary().items()}}

    def _rows(self) -> tuple[list[str], list[list[str]]]:
        head = ["scenario"] + [f"{lab} {col}" for lab in self.labels for col in ("J", "e_max [m]")]
        m = self.scores.metrics
        rows = [[name] + [_num(m[p, s, k]) for p in range(len(self.labels)) for k in (0, 1)]
                for s, name in enumerate(self.scores.names)]
        summary = self.summary()
        for key in next(iter(summary.values())):
            label = "diverged" if key == "diverged" else f"{key} J"
            rows.append([f"**{label}**"] + [x for lab in self.labels for x in (
                str(summary[lab][key]) if key == "diverged" else _num(summary[lab][key]), "")])
        return head, rows

    def markdown(self) -> str:
        head, rows = self._rows()
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rows]
        return "\n".join(lines) + "\n"

    def text(self) -> str:
        head, rows = self._rows()
        rows = [[c.replace("**", "") for c in r] for r in rows]
        width = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
        fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(width))
        return "\n".join(fmt.format(*r).rstrip() for r in [head] + rows)


def _num(v: float) -> str:
    return "inf" if math.isinf(v) else f"{v:.4e}"


def scenario_kind(scenario) -> str:
    """What a scenario changes, for grouping: ``road`` (it sets the reference),
    else ``drift`` (the plant; its sensors may be noisy too), else ``noise``,
    else ``nominal``; ``other`` if it does not say (no ``overrides``)."""
    overrides = getattr(scenario, "overrides", None)
    if overrides is None:
        return "other"
    keys = [str(k) for k, _ in overrides]
    for kind, prefix in (("road", "reference."), ("drift", "plant."), ("noise", "noise.")):
        if any(k.startswith(prefix) for k in keys):
            return kind
    return "nominal"


def robustness_table(gains: Sequence[Sequence[float]], labels: Sequence[str], cfg: Config,
                     scenarios: Sequence[Scenario], aggregate: Aggregate,
                     batch: Callable[[np.ndarray, list], np.ndarray] | None = None) -> RobustnessTable:
    """Score each gain set on every scenario over ``cfg`` (each under a label of its own)."""
    if len(labels) != len(gains):
        raise ConfigError(f"{len(labels)} labels for {len(gains)} gain sets: one label each")
    dup = next((lab for i, lab in enumerate(labels) if lab in labels[:i]), None)
    if dup is not None:
        raise ConfigError(f"label {dup!r}: names two gain sets; give each --gains a --label of its own")
    g = np.array([[float(v) for v in k] for k in gains])
    scores = evaluate_scenarios(g, cfg, scenarios, aggregate, batch or evaluate_configs)
    return RobustnessTable(tuple(labels), tuple(tuple(map(float, k)) for k in g), scores,
                           tuple(scenario_kind(s) for s in scenarios))
