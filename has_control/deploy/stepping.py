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

The in-process kernel (:mod:`.guarded`) calls these inside its loop;
:class:`Deployer` calls them per message for a node that watches a running
machine's topics (:mod:`has_control.nodes.deploy_node`). No ROS here.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from has_control.core.cost import score_series
from has_control.core.jit import LEAF
from has_control.deploy.watchdog import (REASONS, SAMPLES, TRIPPED, WATCHDOG_STATE, WatchdogLimits, watchdog_reset,
                                         watchdog_update)

#: Slots of the plan's state: the next row to take, 0/1/2 (stepping / on the last held row / on the safe
#: gains), then the first trip (sample, reason, step) and the second (sample, reason); −1 where none.
STEP, FALLEN, TRIP_AT, TRIP_REASON, TRIP_STEP, TRIP2_AT, TRIP2_REASON = range(7)
PLAN_STATE = 7


def plan_state() -> np.ndarray:
    d = np.full(PLAN_STATE, -1.0)
    d[STEP] = d[FALLEN] = 0.0
    return d


@njit(**LEAF)
def plan_switch(d, i, switches, w):
    """The row of the schedule due at sample ``i`` of the deployment (−1: none)."""
    step = int(d[STEP])
    if d[FALLEN] == 0.0 and step < switches.shape[0] and i >= switches[step]:
        watchdog_reset(w)
        d[STEP] = step + 1
        return step
    return -1


@njit(**LEAF)
def plan_watch(d, w, i, u, e1, lim):
    """Sample ``i``'s command u [m] and error e1 [m] into the watchdog; the row
    to fall back to on a trip (−1: none)."""
    reason = watchdog_update(w, u, e1, lim)
    step = int(d[STEP])
    fallen = int(d[FALLEN])
    if step < 2 and fallen == 0:
        reason = 0                   # the safe gains' settling is the machine before the deployment
    if reason == 0 or fallen >= 2:
        return -1
    if fallen == 0:
        d[TRIP_AT], d[TRIP_REASON], d[TRIP_STEP] = i, reason, step - 1
        back = max(step - 2, 0)      # the row before the one in effect: it held a whole step
        d[FALLEN] = 1.0 if back > 0 else 2.0
    else:
        d[TRIP2_AT], d[TRIP2_REASON] = i, reason
        back = 0
        d[FALLEN] = 2.0
    watchdog_reset(w)
    w[TRIPPED] = 0.0
    w[SAMPLES] = -lim[7]             # judge the fallback gains only after a whole window of them
    return back


class Deployer:
    """The plan driven by messages: :meth:`sample` once per sample seen on the
    running machine, with its index (from the sample's time), the command u
    [m] and the error e1 [m]; it returns the row whose gains must now be set
    (−1: none). Samples may be missed (a lossy topic): a step falls due at the
    first sample at or after its switch. Keeps the series it saw for the
    report and the bag."""

    def __init__(self, schedule: np.ndarray, switches: np.ndarray, limits: WatchdogLimits, dt: float,
                 end: int | None = None):
        """``end``: the plan's length [samples] (default: the last step held as long as the one before)."""
        limits.check()
        self.schedule = np.ascontiguousarray(schedule, dtype=np.float64)
        self.switches = np.ascontiguousarray(switches, dtype=np.int64)
        self.lim = limits.as_array(dt)
        self.dt = dt
        self.d, self.w = plan_state(), np.zeros(WATCHDOG_STATE)
        self.first: int | None = None
        self.rows: list[tuple[int, int, str]] = []     # (sample, row, why) of every change asked for
        self.series: list[tuple[float, float, float, float]] = []   # (t [s], u [m], e1 [m], reason)
        self.last = -1
        if end is None:
            end = int(self.switches[-1] + (self.switches[-1] - self.switches[-2] if len(self.switches) > 1 else 0))
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
        row = plan_switch(self.d, k, self.switches, self.w)
        if row >= 0:
            self.rows.append((i, row, "step" if row > 0 else "safe gains"))
        back = plan_watch(self.d, self.w, k, u, e1, self.lim)
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

    def cost(self, ep: np.ndarray, since: int | None = None) -> float:
        """J (SPEC §6's sum, λ's of ``ep``) of the samples seen from absolute sample ``since`` on."""
        if not self.series:
            return math.nan
        s = np.array(self.series)
        if since is not None and self.first is not None:
            s = s[np.rint(s[:, 0] / self.dt).astype(np.int64) >= since]
        if not len(s):
            return math.nan
        return float(score_series(np.ascontiguousarray(s[:, 2]), np.ascontiguousarray(s[:, 1]), ep)[0])


__all__ = ["plan_state", "plan_switch", "plan_watch", "Deployer", "PLAN_STATE"]
