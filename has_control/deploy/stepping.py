"""The deployment's stepping policy, one implementation for every path: when
the next gains take effect, and which gains the watchdog falls back to.

A plan is a schedule of gain rows (row 0 the safe gains, rows 1 … N the
steps; :meth:`~has_control.deploy.guarded.DeploymentPlan.schedule`) and the
sample at which each row is due (``switches``, counted from the start of the
deployment). Two compiled calls a sample, on a state array ``d``
(PLAN_STATE slots) and the watchdog's state ``w``:

* :func:`plan_switch` before the sample: the row due now (−1: none), the
  watchdog's windows started again for it; no step is taken after a trip;
* :func:`plan_watch` after it: the sample's command u [m] and error e1 [m]
  into the watchdog (:func:`~has_control.deploy.watchdog.watchdog_update`),
  and on a trip the row to fall back to: the row before the one in effect
  (it held a whole step; the safe gains before any), and on a second trip
  the safe gains. The settling on the safe gains (before the first step) is
  not judged. The fallback gains are judged only after a whole window of them.
  The command-power limit is at least BASELINE_FACTOR (3) times the safe
  gains' own RMS above the corner as the settling ends (a mean over the last
  ~0.1 s, kept by :func:`plan_watch`, which raises ``lim`` once at the first
  judged sample): a machine whose safe gains already exceed the limit is not
  tripped for what it always does.

The deployment keeps the better of what it measured (when the plan asks for a
comparison: ``compare`` = (sample V, window W [samples], margin)). From sample
V on (the last step held a whole hold), :func:`plan_switch` runs an A/B test:
the safe gains for W samples, then the gains that held (the tuned ones, or the
step the watchdog fell back to) for W samples, each window's J summed by
:func:`plan_cost` (SPEC §6's increment of the sample's e1 and u, what the
watchdog reads), then at V + 2W it keeps the held gains only when their J is
below the safe gains' by more than the margin (J_held < (1 − margin)·J_safe),
else it sets the safe gains again. Both windows start on a change of gains and
have one length; with W a whole number of the reference's periods they cover
the same segment of it. A trip during the comparison ends it on the safe gains;
on the safe gains already (a second trip) there is nothing to compare.

The in-process kernel (:mod:`.guarded`) calls these inside its loop;
:class:`Deployer` calls them per message for a node that watches a running
machine's topics (:mod:`has_control.nodes.deploy_node`). No ROS here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from has_control.core.cost import cost_increment, score_series
from has_control.core.jit import LEAF
from has_control.deploy.watchdog import (POWER, REASONS, SAMPLES, TRIPPED, WATCHDOG_STATE, WatchdogLimits,
                                         watchdog_reset, watchdog_update)

#: Slots of the plan's state: the next row to take, 0/1/2 (stepping / on the last held row / on the safe
#: gains), then the first trip (sample, reason, step) and the second (sample, reason); −1 where none;
#: the row in effect; the comparison's start V (−1: none), window W [samples] and margin, its phase
#: (COMPARE_PHASES), the row it measures against the safe gains, the two windows' J and the row kept (−1: none yet).
(STEP, FALLEN, TRIP_AT, TRIP_REASON, TRIP_STEP, TRIP2_AT, TRIP2_REASON, ROW, CMP_AT, CMP_LEN, CMP_MARGIN, PHASE,
 HELD, J_SAFE, J_HELD, KEPT, BASE_HF, HF_LIMIT) = range(18)
PLAN_STATE = 18
#: The watchdog's command-power limit is at least this times the safe gains' own RMS above the corner as the
#: settling ends (its mean square over the last ~0.1 s: five times the watchdog's window).
BASELINE_FACTOR = 3.0
BASELINE_WINDOWS = 5.0
#: Phases of the comparison.
NOT_YET, ON_SAFE, ON_HELD, DECIDED, SKIPPED = range(5)
COMPARE_PHASES = {NOT_YET: "not reached", ON_SAFE: "measuring the safe gains", ON_HELD: "measuring the held gains",
                  DECIDED: "decided", SKIPPED: "not run"}


def plan_state(compare: tuple[int, int, float] | None = None) -> np.ndarray:
    """A plan's state; ``compare``: (sample V, window W [samples], margin) of the comparison (None: none)."""
    d = np.full(PLAN_STATE, -1.0)
    d[STEP] = d[FALLEN] = d[ROW] = d[PHASE] = 0.0
    d[J_SAFE] = d[J_HELD] = 0.0
    d[BASE_HF], d[HF_LIMIT] = 0.0, -1.0
    if compare is not None:
        at, n, margin = compare
        if not (at >= 0 and n >= 1 and 0.0 <= margin < 1.0):
            raise ValueError(f"comparison {compare!r}: expected a start >= 0, a window >= 1 sample, 0 <= margin < 1")
        d[CMP_AT], d[CMP_LEN], d[CMP_MARGIN] = at, n, margin
    return d


@njit(**LEAF)
def plan_switch(d, i, switches, w):
    """The row of the schedule due at sample ``i`` of the deployment (−1: none)."""
    step = int(d[STEP])
    if d[FALLEN] == 0.0 and step < switches.shape[0] and i >= switches[step]:
        watchdog_reset(w)
        d[STEP] = step + 1
        d[ROW] = step
        return step
    if d[CMP_AT] >= 0.0:
        return _compare_switch(d, i, w)
    return -1


@njit(**LEAF)
def _compare_switch(d, i, w):
    """The comparison's changes of gains (see the module)."""
    phase = int(d[PHASE])
    at, n = d[CMP_AT], d[CMP_LEN]
    if phase == NOT_YET and i >= at:
        if d[FALLEN] >= 2.0:
            d[PHASE], d[KEPT] = SKIPPED, 0.0       # on the safe gains already
            return -1
        d[HELD], d[PHASE], d[ROW] = d[ROW], ON_SAFE, 0.0
        watchdog_reset(w)
        return 0
    if phase == ON_SAFE and i >= at + n:
        d[PHASE], d[ROW] = ON_HELD, d[HELD]
        watchdog_reset(w)
        return int(d[HELD])
    if phase == ON_HELD and i >= at + 2.0 * n:
        d[PHASE] = DECIDED
        if d[J_HELD] < (1.0 - d[CMP_MARGIN]) * d[J_SAFE]:
            d[KEPT] = d[HELD]
            return -1
        d[KEPT], d[ROW] = 0.0, 0.0
        watchdog_reset(w)
        return 0
    return -1


@njit(**LEAF)
def plan_cost(d, u, e1, ep):
    """Sample's command u [m] and error e1 [m] into the comparison's window in progress (λ's and Δt of ``ep``)."""
    phase = int(d[PHASE])
    if phase == ON_SAFE:
        d[J_SAFE] += cost_increment(e1, u, ep)
    elif phase == ON_HELD:
        d[J_HELD] += cost_increment(e1, u, ep)


@njit(**LEAF)
def plan_watch(d, w, i, u, e1, lim):
    """Sample ``i``'s command u [m] and error e1 [m] into the watchdog; the row
    to fall back to on a trip (−1: none)."""
    step = int(d[STEP])
    settling = step < 2 and d[FALLEN] == 0.0
    if not settling and d[HF_LIMIT] < 0.0:
        # a limit cycle is what the safe gains do not do: a machine whose safe gains already put more command
        # above the corner than the limit (noise through a derived velocity) is judged against their own
        lim[2] = max(lim[2], BASELINE_FACTOR * math.sqrt(max(d[BASE_HF], 0.0)))
        d[HF_LIMIT] = lim[2]
    reason = watchdog_update(w, u, e1, lim)
    if settling:
        # the safe gains' own command power above the corner [m²], a slow mean of the watchdog's window
        d[BASE_HF] += lim[1] / BASELINE_WINDOWS * (w[POWER] - d[BASE_HF])
    fallen = int(d[FALLEN])
    if step < 2 and fallen == 0:
        reason = 0                   # the safe gains' settling is the machine before the deployment
    if reason == 0 or fallen >= 2:
        return -1
    phase = int(d[PHASE])
    if phase == ON_SAFE or phase == ON_HELD:    # a trip ends the comparison on the safe gains
        d[PHASE], d[KEPT] = SKIPPED, 0.0
    if phase == ON_SAFE or phase == ON_HELD or d[ROW] == 0.0:
        if fallen == 0:
            d[TRIP_AT], d[TRIP_REASON], d[TRIP_STEP] = i, reason, step - 1
        else:
            d[TRIP2_AT], d[TRIP2_REASON] = i, reason
        back = 0
        d[FALLEN] = 2.0
    elif fallen == 0:
        d[TRIP_AT], d[TRIP_REASON], d[TRIP_STEP] = i, reason, step - 1
        back = max(step - 2, 0)      # the row before the one in effect: it held a whole step
        d[FALLEN] = 1.0 if back > 0 else 2.0
    else:
        d[TRIP2_AT], d[TRIP2_REASON] = i, reason
        back = 0
        d[FALLEN] = 2.0
    d[ROW] = back
    watchdog_reset(w)
    w[TRIPPED] = 0.0
    w[SAMPLES] = -lim[7]             # judge the fallback gains only after a whole window of them
    return back


def _why(before: int, after: int, row: int) -> str:
    """Why a row was asked for, from the comparison's phase before and after the call."""
    if after != before:
        return {ON_SAFE: "comparison: the safe gains", ON_HELD: "comparison: the held gains",
                DECIDED: "comparison: kept the safe gains"}.get(after, "comparison")
    return "step" if row > 0 else "safe gains"


@dataclass(frozen=True)
class Comparison:
    """The comparison's outcome: window [s] each, margin [-], J of the safe
    gains' window and of the held gains' (the row ``held``: the tuned ones
    unless the watchdog fell back), the row kept, the phase it ended in."""

    window: float
    margin: float
    safe_J: float
    held_J: float
    held: int
    kept: int
    phase: str

    @property
    def ratio(self) -> float:
        return self.held_J / self.safe_J if self.safe_J > 0.0 else math.nan

    def line(self, steps: int) -> str:
        which = "the tuned gains" if self.held == steps else f"step {self.held}'s gains"
        if self.phase != COMPARE_PHASES[DECIDED]:
            return (f"compared: not run to its end ({self.phase}); kept the safe gains" if self.kept == 0 else
                    f"compared: not run ({self.phase})")
        verdict = (f"kept {which}" if self.kept == self.held else
                   f"KEPT THE SAFE GAINS: {which} measured {self.ratio:.4g}x the safe gains' J, "
                   f"not below 1 - {self.margin:g}")
        return (f"compared over {self.window:g} s each (safe gains, then {which}): J {self.safe_J:.6e} against "
                f"{self.held_J:.6e} ({self.ratio:.4g}x); {verdict}")

    def as_json(self) -> dict:
        f = lambda v: v if math.isfinite(v) else None  # noqa: E731
        return {"window": self.window, "margin": self.margin, "safe_J": f(self.safe_J), "held_J": f(self.held_J),
                "ratio": f(self.ratio), "held": self.held, "kept": self.kept, "phase": self.phase,
                "kept_safe": self.kept == 0}


def comparison_of(d: np.ndarray, dt: float) -> Comparison | None:
    """The :class:`Comparison` of a plan's state ``d`` (None: no comparison asked for)."""
    if d[CMP_AT] < 0.0:
        return None
    return Comparison(float(d[CMP_LEN] * dt), float(d[CMP_MARGIN]), float(d[J_SAFE]), float(d[J_HELD]),
                      int(d[HELD]), int(d[KEPT]), COMPARE_PHASES[int(d[PHASE])])


class Deployer:
    """The plan driven by messages: :meth:`sample` once per sample seen on the
    running machine, with its index (from the sample's time), the command u
    [m] and the error e1 [m]; it returns the row whose gains must now be set
    (−1: none). Samples may be missed (a lossy topic): a step falls due at the
    first sample at or after its switch. Keeps the series it saw for the
    report and the bag."""

    def __init__(self, schedule: np.ndarray, switches: np.ndarray, limits: WatchdogLimits, dt: float,
                 end: int | None = None, compare: tuple[int, int, float] | None = None,
                 ep: np.ndarray | None = None):
        """``end``: the plan's length [samples] (default: the last step held as long as the one before, then
        the comparison); ``compare``: (V, W, margin) of :func:`plan_state`, with ``ep`` the cost's array
        (:meth:`~has_control.core.params.Episode.as_array`: its λ's and Δt)."""
        limits.check()
        if compare is not None and ep is None:
            raise ValueError("a comparison needs the cost's array ep")
        self.schedule = np.ascontiguousarray(schedule, dtype=np.float64)
        self.switches = np.ascontiguousarray(switches, dtype=np.int64)
        self.lim = limits.as_array(dt)
        self.dt = dt
        self.ep = np.ascontiguousarray(ep, dtype=np.float64) if ep is not None else np.zeros(0)
        self.d, self.w = plan_state(compare), np.zeros(WATCHDOG_STATE)
        self.first: int | None = None
        self.rows: list[tuple[int, int, str]] = []     # (sample, row, why) of every change asked for
        self.series: list[tuple[float, float, float, float]] = []   # (t [s], u [m], e1 [m], reason)
        self.last = -1
        if end is None:
            end = int(self.switches[-1] + (self.switches[-1] - self.switches[-2] if len(self.switches) > 1 else 0))
            if compare is not None:
                end = max(end, int(compare[0] + 2 * compare[1]))
        self.end = end                                 # relative to the first sample seen

    def done(self) -> bool:
        return self.first is not None and self.last - self.first >= self.end

    def sample(self, i: int, u: float, e1: float) -> int:
        """Sample ``i`` (absolute); the row to set now, or −1."""
        if i <= self.last:
            return -1                                  # a sample seen again, or out of order
        if self.first is None:
            self.first = i
        self.last = i
        k = i - self.first
        phase = int(self.d[PHASE])
        row = plan_switch(self.d, k, self.switches, self.w)
        if row >= 0:
            self.rows.append((i, row, _why(phase, int(self.d[PHASE]), row)))
        back = plan_watch(self.d, self.w, k, u, e1, self.lim)
        if self.ep.shape[0]:
            plan_cost(self.d, u, e1, self.ep)
        reason = 0
        if back >= 0:
            reason = int(self.d[TRIP2_REASON] if self.d[TRIP2_AT] >= 0 else self.d[TRIP_REASON])
            self.rows.append((i, back, f"fallback: {REASONS.get(reason, '?')}"))
        self.series.append((i * self.dt, u, e1, float(reason)))
        return back if back >= 0 else row

    def tripped(self) -> tuple[int, str, int] | None:
        """(sample, reason, step) of the first trip, or None."""
        if self.d[TRIP_AT] < 0:
            return None
        return int(self.d[TRIP_AT]) + self.first, REASONS.get(int(self.d[TRIP_REASON]), "?"), int(self.d[TRIP_STEP])

    def second_trip(self) -> int | None:
        return int(self.d[TRIP2_AT]) + self.first if self.d[TRIP2_AT] >= 0 else None

    def final_row(self) -> int:
        """The row in effect at the end (as asked for)."""
        return self.rows[-1][1] if self.rows else 0

    def comparison(self) -> Comparison | None:
        """What the comparison measured and kept (None: the plan asked for none)."""
        return comparison_of(self.d, self.dt)

    def cost(self, ep: np.ndarray, since: int | None = None, until: int | None = None) -> float:
        """J (SPEC §6's sum, λ's of ``ep``) of the samples seen from absolute sample ``since`` on (before
        ``until``)."""
        if not self.series:
            return math.nan
        s = np.array(self.series)
        i = np.rint(s[:, 0] / self.dt).astype(np.int64)
        if since is not None and self.first is not None:
            s, i = s[i >= since], i[i >= since]
        if until is not None:
            s = s[i < until]
        if not len(s):
            return math.nan
        return float(score_series(np.ascontiguousarray(s[:, 2]), np.ascontiguousarray(s[:, 1]), ep)[0])


__all__ = ["plan_state", "plan_switch", "plan_watch", "plan_cost", "Deployer", "Comparison", "comparison_of",
           "PLAN_STATE"]
