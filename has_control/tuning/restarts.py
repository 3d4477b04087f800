"""Restarted CMA-ES with a local polish: the default tuning method ``cma-restarts``.

The global phase runs ``side_by_side`` small CMA-ES searches (pycma's
:class:`cma.CMAEvolutionStrategy`, population 7 for three gains) at once:
their candidates go to the objective in one batch, so a batch evaluator keeps
every core busy although each search is small. Each search starts at a seeded
random point of the box with a step of ``sigma`` (a fraction of the box) and
ends when it has converged (its best J changed by less than ``tolerance``, a
fraction of J, over ``window`` generations, or pycma's own ``tolx``); a new
search takes its place: from where it ended with the small step
``polish_sigma`` when it found the best J so far (a refinement), else from a
new random point. When the evaluations left
are ``polish`` or fewer (at most a third of the budget), the global phase ends and the best ``polish_starts``
distinct points found are refined side by side by CMA-ES with a small step
``polish_sigma``, until they converge or the budget ``evaluations`` is spent.
pycma's box handling (``BoundTransform``) keeps every candidate in the box and
lets a search converge onto a bound.

The search works on the box scaled to [0, 1]^M, linearly or (``scale: log``)
in log k.

Ask/tell: :meth:`Restarts.ask` gives the (P, M) candidates, :meth:`Restarts.tell`
their P costs (NaN counts as +inf). Every random draw comes from one NumPy
PCG64 generator seeded by ``seed`` (pycma is given it as ``randn``; the global
``numpy.random`` is never touched), and the algorithm is a pure function of the
seed and the costs told. The checkpoint is therefore the list of costs told so
far: :meth:`Restarts.from_state` replays them (no evaluation) and checks that
the replay asks for the very candidates recorded, bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Iterator

import numpy as np

from has_control.common.errors import shown
from has_control.tuning.optimiser import (
    BestSoFar, IterationRecord, SwarmError, SwarmResult, check_bounds as _check_bounds, record_dict, record_from,
)

if TYPE_CHECKING:                    # pycma is imported where a search starts (see _search)
    import cma

METHOD = "cma-restarts"
SCALES = ("linear", "log")
MAX_EVALUATIONS = 10_000_000
MAX_POPULATION = 10_000


@dataclass(frozen=True)
class RestartSettings:
    """Settings of ``cma-restarts`` (the ``restarts.*`` keys of config/tuner.yaml).

    evaluations: the budget (every candidate scored counts one; the last
    generation may pass it by less than a population); population:
    λ of each CMA-ES search; side_by_side: searches whose candidates share one
    batch; sigma: initial step as a fraction of the (scaled) box; tolerance,
    window: a search has converged when its best J over the last ``window``
    generations spans less than ``tolerance`` × J; polish: evaluations kept
    for the polish (at most a third of the budget); polish_starts: distinct best points polished;
    polish_sigma: their initial step; scale: 'linear' or 'log' (search in log k).
    """

    evaluations: int = 4000
    population: int = 7
    side_by_side: int = 2
    sigma: float = 0.3
    tolerance: float = 1e-5
    window: int = 10
    polish: int = 600
    polish_starts: int = 2
    polish_sigma: float = 0.02
    scale: str = "log"

    def validate(self) -> "RestartSettings":
        def bad(name, why):
            raise SwarmError(f"restarts.{name} = {shown(getattr(self, name))}: {why}", key=name)
        for name in ("evaluations", "population", "side_by_side", "window", "polish", "polish_starts"):
            v = getattr(self, name)
            low = 0 if name == "polish" else (2 if name == "population" else 1)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                bad(name, f"must be a whole number >= {low}")
        if self.evaluations > MAX_EVALUATIONS:
            bad("evaluations", f"more than the limit of {MAX_EVALUATIONS:,}")
        if self.population * self.side_by_side > MAX_POPULATION:
            bad("side_by_side", f"{self.side_by_side} searches x population {self.population} is more than "
                                f"{MAX_POPULATION:,} candidates per batch")
        for name in ("sigma", "polish_sigma", "tolerance"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                bad(name, "must be a finite number > 0")
        if self.sigma > 1 or self.polish_sigma > 1:
            bad("sigma" if self.sigma > 1 else "polish_sigma", "must be <= 1 (a fraction of the box)")
        if self.scale not in SCALES:
            bad("scale", f"expected one of {', '.join(SCALES)}")
        return self


class Restarts(BestSoFar):
    """``cma-restarts`` driven by ask/tell (see the module's docstring)."""

    name = METHOD

    def __init__(self, bounds, settings: RestartSettings | None = None, seed: int | None = None):
        self.settings = (settings or RestartSettings()).validate()
        self.lower, self.upper = _check_bounds(bounds)
        if self.settings.scale == "log" and np.any(self.lower <= 0):
            raise SwarmError(f"restarts.scale = 'log': needs bounds > 0, lower is {self.lower.tolist()}", key="scale")
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.gbest_x = self.lower + 0.5 * (self.upper - self.lower)
        self.gbest_f = math.inf
        self.iteration = 0
        self.evaluations = 0
        self.nan_costs = 0
        self.searches = 0                    # CMA-ES searches started (global phase and polish)
        self.phase = "global"
        self.stop_reason: str | None = None
        self.history: list[IterationRecord] = []
        self._steps = self._run()
        try:
            self._pending = next(self._steps)
        except StopIteration:
            self._pending = np.empty((0, self.lower.size))

    # --- scaling ------------------------------------------------------------
    def _to_gains(self, z: np.ndarray) -> np.ndarray:
        z = np.clip(z, 0.0, 1.0)
        if self.settings.scale == "log":
            lo, hi = np.log(self.lower), np.log(self.upper)
            return np.clip(np.exp(lo + z * (hi - lo)), self.lower, self.upper)
        return self.lower + z * (self.upper - self.lower)

    # --- the algorithm: a generator of batches, sent their costs -------------
    def _search(self, z0: np.ndarray, sigma: float) -> "cma.CMAEvolutionStrategy":
        s = self.settings
        draws = np.random.default_rng(self.rng.integers(2**63))

        def randn(*shape):
            return draws.standard_normal(shape)
        self.searches += 1
        # lazy: pycma loads scipy.stats on import (about 1 s); only a cma-restarts run needs it
        import cma
        return cma.CMAEvolutionStrategy(list(z0), sigma, {
            "bounds": [0.0, 1.0], "popsize": s.population, "seed": np.nan, "randn": randn,
            "verbose": -9, "verb_log": 0, "verb_disp": 0, "tolfun": 0.0, "tolfunhist": 0.0,
            "tolx": 1e-9, "tolflatfitness": s.window, "maxfevals": s.evaluations})

    def _run(self) -> Iterator[np.ndarray]:
        s = self.settings
        m = self.lower.size
        found: list[tuple[float, np.ndarray]] = []            # (J, z) at which searches ended
        polish = min(s.polish, s.evaluations // 3)
        runs = [[self._search(self.rng.uniform(0.0, 1.0, m), s.sigma), [], False] for _ in range(s.side_by_side)]
        while s.evaluations - self.evaluations > polish:
            left = s.evaluations - polish - self.evaluations
            keep = max(1, math.ceil(left / s.population))
            found += [(float(es.best.f), np.array(es.best.x)) for es, _, _ in runs[keep:] if es.best.x is not None]
            runs = runs[:keep]
            asked = [es.ask() for es, _, _ in runs]
            costs = yield np.vstack([self._to_gains(np.array(z)) for z in asked])
            for i, ((es, bests, refining), z) in enumerate(zip(runs, asked)):
                f = costs[i * s.population:(i + 1) * s.population]
                es.tell(z, [float(v) for v in f])
                bests.append(float(np.min(f)))
                if self._converged(es, bests):
                    best = not found or es.best.f < min(q for q, _ in found)
                    found.append((float(es.best.f), np.array(es.best.x)))
                    if best and not refining:        # a new best basin: refine it with a small step at once
                        runs[i] = [self._search(np.array(es.best.x), s.polish_sigma), [], True]
                    else:
                        runs[i] = [self._search(self.rng.uniform(0.0, 1.0, m), s.sigma), [], False]
        self.phase = "polish"
        found += [(float(es.best.f), np.array(es.best.x)) for es, _, _ in runs if es.best.x is not None]
        starts = _distinct(found, s.polish_starts)
        runs = [[self._search(z, s.polish_sigma), []] for z in starts]
        while runs and self.evaluations < s.evaluations:
            left = s.evaluations - self.evaluations
            runs = runs[:max(1, math.ceil(left / s.population))]
            asked = [es.ask() for es, _ in runs]
            costs = yield np.vstack([self._to_gains(np.array(z)) for z in asked])
            for i, ((es, bests), z) in enumerate(zip(runs, asked)):
                f = costs[i * s.population:(i + 1) * s.population]
                es.tell(z, [float(v) for v in f])
                bests.append(float(np.min(f)))
            runs = [r for r in runs if not self._converged(*r)]
        self.stop_reason = (f"spent the budget of {s.evaluations} evaluations" if self.evaluations >= s.evaluations
                            else "the polish converged")

    def _converged(self, es: "cma.CMAEvolutionStrategy", bests: list[float]) -> bool:
        s = self.settings
        if es.stop():
            return True
        if len(bests) < s.window:
            return False
        recent = bests[-s.window:]
        low = min(recent)
        return math.isfinite(low) and max(recent) - low <= s.tolerance * abs(low)

    # --- ask / tell -----------------------------------------------------------
    def progress(self) -> float:
        """Share of the budget spent, 0 .. 1."""
        return 1.0 if self.done else min(1.0, self.evaluations / self.settings.evaluations)

    def ask(self) -> np.ndarray:
        """Candidates to evaluate now, (P, M). Raises once the method has stopped."""
        if self.done:
            raise SwarmError(f"{METHOD} has stopped: {self.stop_reason}")
        return self._pending.copy()

    def tell(self, costs) -> None:
        """Costs of the candidates from :meth:`ask`; NaN counts as +inf."""
        x = self._pending
        f = np.array(costs, dtype=np.float64).ravel()
        if f.shape != (x.shape[0],):
            raise SwarmError(f"tell: expected {x.shape[0]} costs, got {f.size}")
        nan = np.isnan(f)
        self.nan_costs += int(nan.sum())
        f[nan] = np.inf
        self.evaluations += f.size
        i = int(np.argmin(f))
        if f[i] < self.gbest_f:
            self.gbest_f, self.gbest_x = float(f[i]), x[i].copy()
        finite = f[np.isfinite(f)]
        self.history.append(IterationRecord(
            self.iteration, self.gbest_f, self.gbest_x.copy(),
            float(finite.mean()) if finite.size else math.inf,
            float(finite.std()) if finite.size else math.nan, x.copy(), f.copy()))
        self.iteration += 1
        try:
            self._pending = self._steps.send(f)
        except StopIteration:
            self._pending = np.empty((0, x.shape[1]))

    # --- checkpoint -------------------------------------------------------------
    def state_dict(self, history: bool = True) -> dict:
        """What identifies the run (JSON-serialisable). The costs told are in the
        iteration records: without ``history`` they are left out, and
        :meth:`from_state` needs them back (a session bag stores them once each)."""
        return {"method": METHOD, "settings": asdict(self.settings), "lower": self.lower.tolist(),
                "upper": self.upper.tolist(), "seed": self.seed, "iteration": self.iteration,
                "evaluations": self.evaluations, "nan_costs": self.nan_costs, "stop_reason": self.stop_reason,
                "history": [record_dict(h) for h in self.history] if history else []}

    @classmethod
    def from_state(cls, state: dict) -> "Restarts":
        """The run restored by replaying the recorded costs; refuses a record whose
        candidates differ from the replay's (another pycma, another settings)."""
        run = cls((state["lower"], state["upper"]), RestartSettings(**state["settings"]), state["seed"])
        records = [record_from(h) if isinstance(h, dict) else h for h in state.get("history", [])]
        if len(records) != int(state["iteration"]):
            raise SwarmError(f"{METHOD} state: {len(records)} iteration records for iteration {state['iteration']}")
        for rec in records:
            if run.done or not np.array_equal(run._pending, rec.positions):
                raise SwarmError(f"{METHOD} state: iteration {rec.iteration} asked for other candidates than "
                                 "recorded (another cma version or other settings?)")
            run.tell(rec.costs)
            run.nan_costs = 0
        run.nan_costs = int(state["nan_costs"])
        if run.evaluations != int(state["evaluations"]) or run.stop_reason != state["stop_reason"]:
            raise SwarmError(f"{METHOD} state: the replay does not end where the record did")
        return run

    def result(self) -> SwarmResult:
        return SwarmResult(self.gbest_x.copy(), self.gbest_f, self.iteration, self.evaluations,
                           self.stop_reason or "not finished", math.isfinite(self.gbest_f),
                           self.nan_costs, list(self.history))


def _distinct(found: list[tuple[float, np.ndarray]], count: int, radius: float = 0.05) -> list[np.ndarray]:
    """The ``count`` best points, each farther than ``radius`` (in the unit box) from better ones."""
    out: list[np.ndarray] = []
    for f, z in sorted(found, key=lambda p: p[0]):
        if not math.isfinite(f) or len(out) >= count:
            break
        if all(np.linalg.norm(z - o) > radius for o in out):
            out.append(z)
    return out


__all__ = ["Restarts", "RestartSettings", "METHOD"]
