"""Structure selection: which model class explains the recording.

The candidates are options of the plant model (:class:`~has_control.core.params.Plant`):
the valve ideal, a first-order lag or a second-order spool; the command
delayed by 0 or 1 sample; Coulomb friction or none. Each is fitted by
:func:`~has_control.identify.fit.identify` and scored by the Bayesian
information criterion of its residuals in units of the sensors' noise level
(the same, data-based level for every candidate, :func:`~.verdict.noise_levels`):

    BIC = N·ln(SSR/N) + k·ln N,   SSR = Σ (r/σ)²

over the N residuals, k its estimated parameters (the segments' initial
states are the same for every candidate and left out; the residuals are
counted as independent, which they are not quite, so the BIC leans to richer
structures: hence the margin). The search is greedy, as forward selection
is: the three valves without delay or friction first (a richer valve kept
only if it lowers the BIC by BIC_MARGIN); then the chosen valve with a
sample of delay and, separately, with friction, each kept if it lowers the
BIC by BIC_MARGIN; when either did, both together, kept if the pair lowers
it by BIC_MARGIN again (a delay can hide friction and the reverse). With a held-out
run (``--validate``) the chosen structure is also the one whose held-out fit
is not beaten by another's by more than HELD_OUT_MARGIN percentage points
(else that one is chosen, and the reason says so). Every fitted candidate is
reported, with why the chosen one won.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from has_control.identify.data import Experiment, IdentificationError
from has_control.identify.fit import IdentificationResult, identify
from has_control.identify.parameters import DEFAULT_KEYS
from has_control.identify.verdict import noise_levels

#: The physical parameters every candidate estimates (the valve's own come with its structure).
PHYSICAL = tuple(k for k in DEFAULT_KEYS if k != "valve_time_constant")
#: Held-out fit [percentage points, the worst signal] by which another candidate must beat the BIC's choice.
HELD_OUT_MARGIN = 1.0
#: Where a second-order spool's fit starts: ζ, and f_n from the first-order lag's τ as 2ζ/ω_n = τ [Hz].
ZETA_START = 0.7
#: The BIC decrease a structure with more parameters must bring to be preferred ("very strong"
#: evidence on Kass and Raftery's scale).
BIC_MARGIN = 10.0
#: Where friction's fit starts [N].
FRICTION_START = 100.0
#: The valves, by name.
VALVES = ("ideal", "first-order", "second-order")


@dataclass(frozen=True)
class Structure:
    """A candidate: its valve (VALVES), delay [samples] and whether it has friction."""

    valve: str = "first-order"
    delay: int = 0
    friction: bool = False

    @property
    def name(self) -> str:
        return self.valve + (f" +{self.delay} delay" if self.delay else "") + (" +friction" if self.friction else "")

    def keys(self) -> tuple[str, ...]:
        extra = {"ideal": (), "first-order": ("valve_time_constant",),
                 "second-order": ("valve_frequency", "valve_damping_ratio")}[self.valve]
        return PHYSICAL + extra + (("friction_coulomb",) if self.friction else ())

    def plant(self, plant, tau: float):
        """``plant`` (a Plant) with this structure, the spool started from the lag ``tau`` [s]."""
        f = min(max(ZETA_START / (math.pi * tau), 20.0), 1000.0) if tau > 0.0 else 150.0
        changes = {"delay": self.delay, "friction_coulomb": 0.0, "friction_stribeck": 0.0}
        if self.valve == "second-order":
            changes.update(valve_time_constant=0.0, valve_frequency=f, valve_damping_ratio=ZETA_START)
        else:
            changes.update(valve_frequency=0.0)
            if self.valve == "ideal":
                changes.update(valve_time_constant=0.0)
        return dataclasses.replace(plant, **changes)


@dataclass(frozen=True)
class Candidate:
    """A fitted structure: its result (or the one-line reason it failed),
    parameters k, residuals N, BIC, and held-out fit [%] per signal."""

    structure: Structure
    result: IdentificationResult | None
    k: int
    n: int
    bic: float
    failed: str = ""
    held_out: dict | None = None

    def as_json(self) -> dict:
        return {"structure": self.structure.name, "parameters": self.k, "residuals": self.n,
                "bic": self.bic if math.isfinite(self.bic) else None, "failed": self.failed or None,
                "adequate": self.result.verdict.adequate if self.result and self.result.verdict else None,
                "held_out_fit_percent": self.held_out}


@dataclass(frozen=True)
class Selection:
    """Every candidate fitted, the chosen one and why."""

    candidates: list[Candidate]
    chosen: Candidate
    why: str

    def as_json(self) -> dict:
        return {"chosen": self.chosen.structure.name, "why": self.why,
                "candidates": [c.as_json() for c in self.candidates],
                "criterion": "BIC = N ln(SSR/N) + k ln N, residuals in units of the data's noise level"}

    def table(self) -> str:
        lines = [f"{'structure':<30}{'k':>3}{'BIC':>16}{'dBIC':>12}  verdict"]
        best = self.chosen.bic
        for c in self.candidates:
            mark = "*" if c is self.chosen else " "
            if c.failed:
                lines.append(f"{mark}{c.structure.name:<29}{c.k:>3}{'-':>16}{'-':>12}  failed: {c.failed}")
                continue
            v = c.result.verdict
            verdict = "adequate" if v.adequate else "INADEQUATE"
            held = "" if not c.held_out else "  held-out " + " ".join(f"{x:.1f}" for x in c.held_out.values())
            lines.append(f"{mark}{c.structure.name:<29}{c.k:>3}{c.bic:>16.6g}{c.bic - best:>+12.4g}  {verdict}{held}")
        lines.append(f"structure: {self.chosen.structure.name} ({self.why})")
        return "\n".join(lines)


def _bic(result: IdentificationResult, sigma: np.ndarray, k: int) -> tuple[float, int]:
    res = result.residuals
    if res is None or len(res) == 0:
        return math.inf, 0
    z = res / sigma
    n = z.size
    ssr = float(np.sum(z * z))
    return n * math.log(max(ssr, 1e-300) / n) + k * math.log(n), n


def _with_structure(exps: list[Experiment], s: Structure, tau: float) -> list[Experiment]:
    return [dataclasses.replace(e, cfg=dataclasses.replace(e.cfg, plant=s.plant(e.cfg.plant, tau))) for e in exps]


def _lag_start(exps: list[Experiment]) -> float:
    """The equation-error estimate of a first-order valve lag [s], where a spool's fit starts."""
    # lazy: segments imports data, which this module's callers import first (no cycle; kept local to the start)
    from has_control.identify.equation_error import equation_error
    from has_control.identify.segments import SEGMENT_SAMPLES, segment_starts
    try:
        tau = equation_error(exps, [segment_starts(e, SEGMENT_SAMPLES) for e in exps], SEGMENT_SAMPLES).get(
            "valve_time_constant", math.nan)
    except (ValueError, np.linalg.LinAlgError):
        tau = math.nan
    return float(tau) if math.isfinite(tau) and tau > 0.0 else 1e-3


def _parallel(fn, items) -> list:
    """``fn`` of each item on two threads (the compiled predictions release the GIL), in order."""
    # lazy: only a structure search starts threads
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(2) as pool:
        return list(pool.map(fn, items))


def fit_structure(exps: list[Experiment], s: Structure, sigma: np.ndarray, tau: float, **options) -> Candidate:
    """Fit one candidate; a failed fit is a candidate with its reason."""
    keys = s.keys()
    start = {}
    if s.valve == "second-order":
        start = {"valve_frequency": min(max(ZETA_START / (math.pi * tau), 20.0), 1000.0) if tau > 0.0 else 150.0,
                 "valve_damping_ratio": ZETA_START}
    if s.friction:
        start["friction_coulomb"] = FRICTION_START
    try:
        res = identify(_with_structure(exps, s, tau), keys, start=start, **options)
    except IdentificationError as exc:
        return Candidate(s, None, len(keys), 0, math.inf, str(exc))
    free = len(res.free)
    bic, n = _bic(res, sigma, free)
    return Candidate(s, res, free, n, bic)


def select_structure(exps: list[Experiment], bounds: dict | None = None, tolerance: float = 0.02,
                     max_evaluations: int = 200, held=None, validate_fn=None) -> Selection:
    """The greedy search of the module over ``exps``. ``held`` and
    ``validate_fn(held, result) -> {signal: fit %}``: the held-out check."""
    known = set().union(*(Structure(v, 1, True).keys() for v in VALVES))
    for k, (lo, hi) in (bounds or {}).items():
        if k not in known:
            raise IdentificationError(f"--bound {k}: not a parameter of any candidate structure "
                                      f"({', '.join(sorted(known))}); --structure given --estimate ... for others")
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise IdentificationError(f"--bound {k} {lo:g} {hi:g}: expected finite LOWER < UPPER")
    sigma = np.sqrt(np.mean([noise_levels(e.x, getattr(e, "gaps", None)) ** 2 for e in exps], axis=0))
    sigma = np.where(sigma > 0.0, sigma, 1.0)
    options = {"tolerance": tolerance, "max_evaluations": max_evaluations}
    tried: list[Candidate] = []

    def fit(s: Structure, tau: float) -> Candidate:
        b = {k: v for k, v in (bounds or {}).items() if k in s.keys()}
        c = fit_structure(exps, s, sigma, tau, bounds=b, **options)
        tried.append(c)
        return c

    tau = _lag_start(exps)
    valves = _parallel(lambda v: fit(Structure(v), tau), VALVES)
    best = valves[0]
    for c in valves[1:]:                     # more of the valve's dynamics only for a clear gain
        if c.bic < best.bic - BIC_MARGIN:
            best = c
    if not math.isfinite(best.bic):
        raise IdentificationError("no candidate structure could be fitted: " + "; ".join(
            f"{c.structure.name}: {c.failed}" for c in tried))
    base = best
    more = _parallel(lambda s: fit(s, tau), (dataclasses.replace(base.structure, delay=1),
                                             dataclasses.replace(base.structure, friction=True)))
    gains = [c for c in more if c.bic < base.bic - BIC_MARGIN]
    if gains:                                # the other extension on top of what helped (forward selection)
        both = fit(dataclasses.replace(base.structure, delay=1, friction=True), tau)
        if both.bic < min(c.bic for c in gains) - BIC_MARGIN:
            gains.append(both)
    best = min(gains, key=lambda c: c.bic) if gains else base
    simpler = sorted((c for c in tried if c is not best and math.isfinite(c.bic) and c.k < best.k),
                     key=lambda c: c.bic)
    richer = [c for c in tried if c is not best and c.k >= best.k and c.structure != best.structure]
    if simpler:
        why = f"BIC {simpler[0].bic - best.bic:.4g} below the simpler {simpler[0].structure.name}"
    else:
        why = "the simplest candidate"
    if richer:
        why += f"; no richer structure lowered it by {BIC_MARGIN:g}"
    tried.sort(key=lambda c: (VALVES.index(c.structure.valve), c.structure.delay, c.structure.friction))
    if held is not None and validate_fn is not None:
        scored = []
        for i, c in enumerate(tried):
            if c.result is not None:
                try:
                    fits = validate_fn(held, c.result)
                except IdentificationError as exc:
                    fits = None
                    tried[i] = dataclasses.replace(c, failed=f"held-out run: {exc}")
                    continue
                tried[i] = dataclasses.replace(c, held_out=fits)
                scored.append(tried[i])
        best = next(c for c in tried if c.structure == best.structure)
        if not best.held_out and scored:                 # its held-out run failed: the best that ran
            rival = min(scored, key=lambda c: c.bic)
            why = f"the lowest BIC whose held-out run could be simulated ({best.structure.name}'s: {best.failed})"
            best = rival
        elif best.held_out:
            worst = min(best.held_out.values())
            rival = max((c for c in scored if c.held_out), key=lambda c: min(c.held_out.values()))
            if min(rival.held_out.values()) > worst + HELD_OUT_MARGIN:
                why = (f"held-out fit {min(rival.held_out.values()):.1f} % against {worst:.1f} % of the lowest "
                       f"BIC ({best.structure.name})")
                best = rival
            else:
                why += f"; held-out worst-signal fit {worst:.1f} %"
        why += " (the held-out run chose among the structures, so its fit is not an independent test)"
    return Selection(tried, best, why)


__all__ = ["Structure", "Candidate", "Selection", "select_structure", "fit_structure", "VALVES"]
