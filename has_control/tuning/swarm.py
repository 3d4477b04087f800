"""Particle-swarm optimisation: PSO, PSO+CP and PSO+CP+TVAC (SPEC §7).

Two interfaces over one implementation:

* :class:`Swarm`, ask/tell: ``x = swarm.ask()`` gives the (N, M) positions to
  evaluate, ``swarm.tell(costs)`` takes their N costs, updates the personal
  and global bests (synchronously) and moves the swarm. Any evaluator works:
  the batch evaluator, the ROS node graph, another machine.
* :func:`minimize`, in the style of ``scipy.optimize``: a plain function that
  calls an objective on the whole swarm and returns a :class:`SwarmResult`.

One seed fixes every random draw (NumPy's PCG64), and the draws per
iteration do not depend on the costs, so the same seed gives the same result
bit for bit. :meth:`Swarm.state_dict` / :meth:`Swarm.from_state` checkpoint
and restore a swarm exactly.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from has_control.common.errors import shown
from has_control.common.json_numbers import list_to_json
from has_control.tuning.optimiser import (  # noqa: F401  (re-exported: the old home of these names)
    BestSoFar, IterationRecord, OptimiseResult, SwarmError, SwarmResult, _from_json, check_bounds as _check_bounds,
    drive, record_dict, record_from,
)


@dataclass(frozen=True)
class Variant:
    """One optimiser of the table: two independent switches."""

    crazy_particles: bool      # redraw velocity components with probability ρc (SPEC §7)
    tvac: bool                 # time-varying acceleration coefficients c1, c2


#: The optimisers by name (choices of the CLI and the ``swarm.variant`` key).
VARIANTS = {"pso": Variant(crazy_particles=False, tvac=False),
            "pso-cp": Variant(crazy_particles=True, tvac=False),
            "pso-cp-tvac": Variant(crazy_particles=True, tvac=True)}
CRAZY_REDRAWS = ("positive", "symmetric")
CRAZY_PROBABILITIES = ("exp-difference", "exp-ratio")
#: Limits checked before a swarm is allocated: positions, velocities and
#: personal bests are particles x dimensions, the history keeps every
#: iteration's positions (particles x iterations x dimensions float64).
MAX_PARTICLES = 100_000
MAX_EVALUATIONS = 10_000_000        # particles x iterations


@dataclass(frozen=True)
class SwarmSettings:
    """Settings of SPEC §7; defaults are the paper's (§5.1).

    variant: 'pso' | 'pso-cp' | 'pso-cp-tvac'; particles N; iterations
    MAXITER; target: stop when gbest cost ≤ target; velocity_limit v_max
    (v_min = −v_max); inertia ω from inertia_max down to inertia_min;
    c1, c2 for PSO and PSO+CP; c1_start … c2_end for TVAC (Ratnaweera et al.);
    crazy_redraw: 'positive' redraws v ~ U(0, v_max) (the paper's Eq. 37),
    'symmetric' v ~ U(−v_max, v_max); crazy_probability: 'exp-difference'
    ρc = ω_min·exp(ω − ω_max) (SPEC's reading) or 'exp-ratio'
    ρc = ω_min·exp(−ω/ω_max) (the alternative).
    """

    variant: str = "pso-cp-tvac"
    particles: int = 80
    iterations: int = 100
    target: float = 1e-10
    velocity_limit: float = 15.0
    inertia_max: float = 1.2
    inertia_min: float = 0.6
    c1: float = 2.0
    c2: float = 2.0
    c1_start: float = 2.5
    c1_end: float = 0.5
    c2_start: float = 0.5
    c2_end: float = 2.5
    crazy_redraw: str = "positive"
    crazy_probability: str = "exp-difference"

    def validate(self) -> "SwarmSettings":
        def bad(name, why):
            raise SwarmError(f"swarm.{name} = {shown(getattr(self, name))}: {why}", key=name)
        if self.variant not in VARIANTS:
            bad("variant", f"expected one of {', '.join(VARIANTS)}")
        if self.crazy_redraw not in CRAZY_REDRAWS:
            bad("crazy_redraw", f"expected one of {', '.join(CRAZY_REDRAWS)}")
        if self.crazy_probability not in CRAZY_PROBABILITIES:
            bad("crazy_probability", f"expected one of {', '.join(CRAZY_PROBABILITIES)}")
        for name in ("particles", "iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                bad(name, "must be a whole number >= 1")
        if self.particles > MAX_PARTICLES:
            bad("particles", f"more than the limit of {MAX_PARTICLES:,}")
        if self.particles * self.iterations > MAX_EVALUATIONS:
            bad("iterations", f"{self.particles} particles x {self.iterations} iterations is more than "
                              f"the limit of {MAX_EVALUATIONS:,} evaluations")
        for name in ("target", "velocity_limit", "inertia_max", "inertia_min", "c1", "c2",
                     "c1_start", "c1_end", "c2_start", "c2_end"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
                bad(name, "expected a number")
            if name != "target" and not math.isfinite(v):
                bad(name, "must be finite")
        if not self.velocity_limit > 0 or not math.isfinite(self.velocity_limit):
            bad("velocity_limit", "must be a finite number > 0")
        if self.inertia_min > self.inertia_max:
            bad("inertia_min", f"exceeds swarm.inertia_max ({self.inertia_max})")
        return self


class Swarm(BestSoFar):
    """A particle swarm driven by ask/tell (SPEC §7)."""

    def __init__(self, bounds, settings: SwarmSettings | None = None, seed: int | None = None):
        self.settings = (settings or SwarmSettings()).validate()
        self.lower, self.upper = _check_bounds(bounds)
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        n, m = self.settings.particles, self.lower.size
        vmax = self.settings.velocity_limit
        self.x = self.rng.uniform(self.lower, self.upper, size=(n, m))
        self.v = self.rng.uniform(-vmax, vmax, size=(n, m))
        self.pbest_x = self.x.copy()
        self.pbest_f = np.full(n, np.inf)
        self.gbest_x = self.x[0].copy()
        self.gbest_f = math.inf
        self.iteration = 0
        self.evaluations = 0
        self.nan_costs = 0
        self.stop_reason: str | None = None
        self.history: list[IterationRecord] = []

    # --- ask / tell ---------------------------------------------------------
    @property
    def name(self) -> str:
        """The method's name (a key of :data:`VARIANTS`)."""
        return self.settings.variant

    def progress(self) -> float:
        """Share of the iterations done, 0 .. 1."""
        return 1.0 if self.done else self.iteration / self.settings.iterations

    def ask(self) -> np.ndarray:
        """Positions to evaluate now, (N, M). Raises if the swarm has stopped."""
        if self.done:
            raise SwarmError(f"swarm has stopped: {self.stop_reason}")
        return self.x.copy()

    def tell(self, costs) -> None:
        """Costs of the positions from :meth:`ask`; NaN counts as +inf."""
        f = np.array(costs, dtype=np.float64).ravel()
        if f.shape != (self.x.shape[0],):
            raise SwarmError(f"tell: expected {self.x.shape[0]} costs, got {f.size}")
        nan = np.isnan(f)
        self.nan_costs += int(nan.sum())
        f[nan] = np.inf
        self.evaluations += f.size
        better = f < self.pbest_f
        self.pbest_f[better] = f[better]
        self.pbest_x[better] = self.x[better]
        i = int(np.argmin(self.pbest_f))
        if self.pbest_f[i] < self.gbest_f:
            self.gbest_f = float(self.pbest_f[i])
            self.gbest_x = self.pbest_x[i].copy()
        finite = f[np.isfinite(f)]
        self.history.append(IterationRecord(
            self.iteration, self.gbest_f, self.gbest_x.copy(),
            float(finite.mean()) if finite.size else math.inf,
            float(finite.std()) if finite.size else math.nan,
            self.x.copy(), f.copy()))
        self.iteration += 1
        if self.gbest_f <= self.settings.target:
            self.stop_reason = f"best cost {self.gbest_f:.6g} reached the target {self.settings.target:g}"
        elif self.iteration >= self.settings.iterations:
            self.stop_reason = f"reached {self.settings.iterations} iterations"
        else:
            self._move(self.iteration - 1)

    def _move(self, it: int) -> None:
        """Velocity and position update of iteration ``it`` (SPEC §7)."""
        s = self.settings
        variant = VARIANTS[s.variant]
        frac = it / s.iterations
        w = s.inertia_max - (s.inertia_max - s.inertia_min) * frac
        if variant.tvac:
            c1 = s.c1_start + (s.c1_end - s.c1_start) * frac
            c2 = s.c2_start + (s.c2_end - s.c2_start) * frac
        else:
            c1, c2 = s.c1, s.c2
        shape = self.x.shape
        r1 = self.rng.random(shape)
        r2 = self.rng.random(shape)
        v = w * self.v + c1 * r1 * (self.pbest_x - self.x) + c2 * r2 * (self.gbest_x - self.x)
        vmax = s.velocity_limit
        v = np.clip(v, -vmax, vmax)
        if variant.crazy_particles:
            rho = crazy_probability(w, s)
            crazy = self.rng.random(shape) <= rho
            low = 0.0 if s.crazy_redraw == "positive" else -vmax
            redraw = self.rng.uniform(low, vmax, size=shape)
            v = np.where(crazy, redraw, v)
        self.v = v
        self.x = np.clip(self.x + v, self.lower, self.upper)

    # --- checkpoint ---------------------------------------------------------
    def state_dict(self, history: bool = True) -> dict:
        """Everything needed to resume exactly (JSON-serialisable); without
        ``history`` the per-iteration records are left out (a session bag
        stores them once each)."""
        return {
            "settings": asdict(self.settings), "lower": self.lower.tolist(),
            "upper": self.upper.tolist(), "seed": self.seed,
            "rng": self.rng.bit_generator.state, "x": self.x.tolist(), "v": self.v.tolist(),
            "pbest_x": self.pbest_x.tolist(), "pbest_f": list_to_json(self.pbest_f),
            "gbest_x": self.gbest_x.tolist(), "gbest_f": list_to_json([self.gbest_f])[0],
            "iteration": self.iteration, "evaluations": self.evaluations,
            "nan_costs": self.nan_costs, "stop_reason": self.stop_reason,
            "history": [record_dict(h) for h in self.history] if history else [],
        }

    @classmethod
    def from_state(cls, state: dict) -> "Swarm":
        sw = cls((state["lower"], state["upper"]), SwarmSettings(**state["settings"]), state["seed"])
        sw.rng.bit_generator.state = state["rng"]
        sw.x = np.array(state["x"], dtype=np.float64)
        sw.v = np.array(state["v"], dtype=np.float64)
        sw.pbest_x = np.array(state["pbest_x"], dtype=np.float64)
        sw.pbest_f = np.array(_from_json(state["pbest_f"]), dtype=np.float64)
        sw.gbest_x = np.array(state["gbest_x"], dtype=np.float64)
        sw.gbest_f = _from_json([state["gbest_f"]])[0]
        sw.iteration = int(state["iteration"])
        sw.evaluations = int(state["evaluations"])
        sw.nan_costs = int(state["nan_costs"])
        sw.stop_reason = state["stop_reason"]
        sw.history = [record_from(h) for h in state.get("history", [])]
        return sw

    def result(self) -> SwarmResult:
        return SwarmResult(self.gbest_x.copy(), self.gbest_f, self.iteration, self.evaluations,
                           self.stop_reason or "not finished", math.isfinite(self.gbest_f),
                           self.nan_costs, list(self.history))


def crazy_probability(w: float, s: SwarmSettings) -> float:
    """ρc of the crazy-particle redraw at inertia ω (see SwarmSettings)."""
    if s.crazy_probability == "exp-ratio":
        return s.inertia_min * math.exp(-w / s.inertia_max)
    return s.inertia_min * math.exp(w - s.inertia_max)


__all__ = ["Swarm", "SwarmSettings", "SwarmResult", "SwarmError", "VARIANTS", "Variant"]
