"""What a deployment through the topics did (ROS-free): the gain changes asked of the
controller, when each took effect, and the report.

The deploy node (:mod:`has_control.nodes.deploy_node`) asks the controller for
each row of the plan's schedule through its parameters (:meth:`Changes.ask`)
and sees on the controller's ``~/gains`` when new gains took effect
(:meth:`Changes.announced`); once the plan has run, :meth:`NodeDeployment.take`
reads the stepping policy's :class:`~has_control.deploy.stepping.Deployer`
(the samples watched, the trips, the cost) into the report. Samples are the loop's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from has_control.deploy.guarded import DeploymentPlan, gap_words
from has_control.deploy.stepping import Comparison


class Changes:
    """The gain changes asked of the controller: [sample asked, row, why, sample it took effect or None]."""

    def __init__(self, schedule):
        self.schedule = schedule                  # the plan's rows of (k1, k2, k3) [1/s]
        self.asked: list[list] = []

    def ask(self, i: int, row: int, why: str) -> None:
        """Row ``row`` of the schedule asked for at sample ``i`` (``why``: the policy's reason)."""
        self.asked.append([i, row, why, None])

    def announced(self, i: int, k) -> None:
        """The controller announced gains ``k`` at sample ``i``: the first announcement of the gains
        asked for (equal to 1e-9 relative), at or after the sample they were asked at, is when they took effect."""
        for entry in self.asked:
            same = all(math.isclose(a, b, rel_tol=1e-9) for a, b in zip(k, self.schedule[entry[1]]))
            if entry[3] is None and entry[0] <= i and same:
                entry[3] = i

    def rows(self) -> list[tuple]:
        return [tuple(e) for e in self.asked]


@dataclass
class NodeDeployment:
    """What a deployment through the topics did. Samples are the loop's;
    ``changes``: (sample asked, row, why, sample it took effect or None)."""

    plan: DeploymentPlan
    step: float
    changes: list = field(default_factory=list)
    tripped: tuple | None = None              # (sample, reason, step)
    second_trip: int | None = None
    first: int | None = None
    last: int | None = None
    J: float = math.nan                        # of the samples watched
    safe_J: float | None = None                # the safe gains alone over the same run (a simulated machine)
    tuned_rate: float | None = None            # J per second on the final gains' step (no trip)
    predicted_J: float | None = None
    predicted_horizon: float | None = None
    final_gains: tuple = ()
    bag: Path | None = None
    comparison: Comparison | None = None       # what the plan's final comparison measured and kept
    hf_limit: float | None = None              # the watchdog's command-power limit in effect [m]

    def take(self, deployer, schedule, ep, changes: Changes) -> None:
        """The plan has run: the samples watched, the trips, J (``ep``: the episode's
        array, the cost's λ's), the final gains and, without a trip, the tuned gains' cost
        rate [1/s] over their step (from when they took effect, else when asked, up to
        the next change: the final comparison's), the comparison and the watchdog's limit in effect."""
        d = deployer
        self.first, self.last = d.first, d.last
        self.tripped, self.second_trip = d.tripped(), d.second_trip()
        self.J = d.cost(ep)
        self.final_gains = tuple(float(v) for v in schedule[d.final_row()])
        self.comparison = d.comparison()
        self.hf_limit = float(d.lim[2])
        asked = changes.asked
        steps = [k for k, e in enumerate(asked) if e[2] == "step"]
        if self.tripped is None and steps:            # the tuned gains' step, up to the next change (if any)
            k = steps[-1]
            since = asked[k][3] if asked[k][3] is not None else asked[k][0]
            until = asked[k + 1][0] if k + 1 < len(asked) else d.last + 1
            if until > since:
                self.tuned_rate = d.cost(ep, since=since, until=until) / ((until - since) * self.step)

    def fallback_latency(self) -> float | None:
        """Seconds of the loop from the sample that tripped to the first sample on the fallback gains."""
        if self.tripped is None:
            return None
        for asked, _row, why, took in self.changes:
            if why.startswith("fallback") and took is not None:
                return (took - self.tripped[0]) * self.step
        return None

    @property
    def gap(self) -> float | None:
        """Measured over predicted J of the tuned gains: the tuned gains' mean cost rate on
        the machine (their step, when no trip) against the prediction's over its horizon."""
        if self.tuned_rate is None or not self.predicted_J or not self.predicted_horizon:
            return None
        return self.tuned_rate / (self.predicted_J / self.predicted_horizon)

    def lines(self) -> list[str]:
        n = (self.last - self.first + 1) if self.first is not None else 0
        out = [f"deployed through the controller's parameters in {self.plan.steps} steps of {self.plan.hold:g} s "
               f"after {self.plan.settle:g} s: {n} samples watched, J = {self.J:.6e}"
               + (f" (safe gains alone {self.safe_J:.6e}, {self.J / self.safe_J:.3g}x)" if self.safe_J else "")]
        for asked, row, why, took in self.changes:
            when = f"took effect at sample {took} (+{took - asked})" if took is not None else "not seen taking effect"
            out.append(f"  sample {asked}: row {row} ({why}), {when}")
        if self.tripped is None:
            out.append(f"watchdog: no trip; final gains ({', '.join(f'{k:.2f}' for k in self.final_gains)})")
        else:
            lat = self.fallback_latency()
            out.append(f"watchdog: TRIPPED at t = {self.tripped[0] * self.step:.4f} s on step {self.tripped[2]} "
                       f"({self.tripped[1]}); fallback in effect "
                       + (f"{lat * 1e3:.1f} ms later" if lat is not None else "not seen")
                       + f"; final gains ({', '.join(f'{k:.2f}' for k in self.final_gains)})")
        if self.comparison is not None:
            out.append(self.comparison.line(self.plan.steps))
        g = self.gap
        if g is not None:
            out.append(f"measured against predicted J: {g:.3g}x ({gap_words(g)}; "
                       f"the tuned gains' cost rate over their step against the prediction's over "
                       f"{self.predicted_horizon:g} s)")
        elif self.predicted_J is not None:
            out.append("measured against predicted J: not measured (the tuned gains did not hold their step)")
        if self.bag is not None:
            out.append(f"wrote {self.bag}")
        return out

    def as_json(self) -> dict:
        f = lambda v: v if v is None or math.isfinite(v) else None  # noqa: E731
        return {"J": f(self.J), "safe_J": self.safe_J,
                "samples": (self.last - self.first + 1) if self.first is not None else 0,
                "tripped": self.tripped is not None,
                "tripped_at": self.tripped[0] * self.step if self.tripped else None,
                "reason": self.tripped[1] if self.tripped else None, "step": self.tripped[2] if self.tripped else None,
                "second_trip_at": self.second_trip * self.step if self.second_trip is not None else None,
                "fallback_latency": self.fallback_latency(), "final_gains": list(self.final_gains),
                "changes": [{"sample": a, "row": r, "why": w, "took_effect": t} for a, r, w, t in self.changes],
                "predicted_J": self.predicted_J, "gap": f(self.gap) if self.gap is not None else None,
                "gap_over_2x": bool(self.gap is not None and self.gap > 2.0),
                "comparison": self.comparison.as_json() if self.comparison is not None else None,
                "hf_limit": self.hf_limit, "bag": str(self.bag) if self.bag else None}
