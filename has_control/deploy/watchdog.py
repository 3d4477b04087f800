"""The deployment watchdog: from the samples of a running loop (the valve
command u [m] and the tracking error e1 [m], one each Δt), does it still
behave, or must the controller fall back to its safe gains?

Three tests, each a requirement a running machine states (``WatchdogLimits``):

* **command power above a frequency**: u minus its first-order low-pass at
  ``corner`` [Hz], its mean square over an exponential window of ``window``
  [s]; trip when its root exceeds ``hf_rms`` [m] (a limit cycle of the valve
  loop is tens of hertz of command);
* **spool at its stop**: the share of samples, over the same window, whose
  command is within 2 % of the travel limit ``valve_limit`` [m]; trip above
  ``stop_share`` (0: the test is off when there is no limit);
* **error growth**: |e1| above ``e1_max`` [m].

The state is a float64 array of WATCHDOG_STATE slots (allocation-free, one
compiled call a sample), so the in-process kernel and a node watching the
topics run the same test. A trip is sticky: the caller falls back once.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from has_control.core.jit import KERNEL, LEAF

#: Slots of the watchdog's state array.
LOW, POWER, AT_STOP, SAMPLES, TRIPPED = range(5)
WATCHDOG_STATE = 5
#: Trip reasons (the value of :func:`watchdog_update`; 0: none).
OK, HF_POWER, AT_THE_STOP, ERROR_GROWTH, NOT_FINITE = range(5)
REASONS = {HF_POWER: "command power above the corner", AT_THE_STOP: "spool at its stop",
           ERROR_GROWTH: "tracking error above its bound", NOT_FINITE: "a non-finite command or error"}


@dataclass(frozen=True)
class WatchdogLimits:
    """What the running machine must keep (see the module). corner [Hz],
    window [s], hf_rms [m], valve_limit [m] (0: no stop test), stop_share [-],
    e1_max [m], arm [s]: how long after a change of gains the window fills
    before the tests count (a tenth of the window by default, so the
    filter's start-up is not a trip)."""

    corner: float = 20.0
    window: float = 0.02
    hf_rms: float = 5.0e-4
    valve_limit: float = 5.0e-3
    stop_share: float = 0.05
    e1_max: float = 0.01
    arm: float = 0.002

    def as_array(self, dt: float) -> np.ndarray:
        """(α of the low-pass, α of the window, hf_rms, stop level, stop_share, e1_max, arming samples,
        the window's samples)."""
        low = 1.0 - math.exp(-2.0 * math.pi * self.corner * dt)
        win = 1.0 - math.exp(-dt / self.window)
        stop = 0.98 * self.valve_limit if self.valve_limit > 0.0 else math.inf
        return np.array([low, win, self.hf_rms, stop, self.stop_share, self.e1_max, math.ceil(self.arm / dt),
                         math.ceil(self.window / dt)])

    def check(self) -> None:
        for name in ("corner", "window", "hf_rms", "e1_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"watchdog.{name} = {v!r}: must be a positive number")
        if not (0.0 < self.stop_share <= 1.0):
            raise ValueError(f"watchdog.stop_share = {self.stop_share!r}: must be in (0, 1]")
        if not (math.isfinite(self.valve_limit) and self.valve_limit >= 0.0):
            raise ValueError(f"watchdog.valve_limit = {self.valve_limit!r}: must be >= 0 (0: no stop test)")


def watchdog_state() -> np.ndarray:
    return np.zeros(WATCHDOG_STATE)


@njit(**LEAF)
def watchdog_reset(w):
    """Start the windows again (after a change of gains); keeps a trip."""
    w[POWER] = 0.0
    w[AT_STOP] = 0.0
    w[SAMPLES] = 0.0


@njit(**LEAF)
def watchdog_update(w, u, e1, lim):
    """One sample of command u [m] and error e1 [m] into state ``w`` with
    limits ``lim`` (:meth:`WatchdogLimits.as_array`); returns the trip reason
    (OK: none). The low-pass starts at the first command it sees."""
    if not (math.isfinite(u) and math.isfinite(e1)):
        w[TRIPPED] = NOT_FINITE
        return NOT_FINITE
    if w[SAMPLES] == 0.0 and w[POWER] == 0.0 and w[LOW] == 0.0:
        w[LOW] = u
    w[LOW] += lim[0] * (u - w[LOW])
    hp = u - w[LOW]
    w[POWER] += lim[1] * (hp * hp - w[POWER])
    w[AT_STOP] += lim[1] * ((1.0 if abs(u) >= lim[3] else 0.0) - w[AT_STOP])
    w[SAMPLES] += 1.0
    reason = OK
    if abs(e1) > lim[5]:
        reason = ERROR_GROWTH
    elif w[SAMPLES] >= lim[6]:
        if math.sqrt(w[POWER]) > lim[2]:
            reason = HF_POWER
        elif w[AT_STOP] > lim[4]:
            reason = AT_THE_STOP
    if reason != OK and w[TRIPPED] == 0.0:
        w[TRIPPED] = reason
    return reason


@njit(**KERNEL)
def watch_series(u, e1, lim, out):
    """:func:`watchdog_update` over recorded series (a bag's, a node's log):
    out[i] the reason at sample i. Returns the first tripped sample, or −1."""
    w = np.zeros(WATCHDOG_STATE)
    first = -1
    for i in range(u.shape[0]):
        out[i] = watchdog_update(w, u[i], e1[i], lim)
        if first < 0 and out[i] != OK:
            first = i
    return first


__all__ = ["WatchdogLimits", "watchdog_state", "watchdog_update", "watchdog_reset", "watch_series", "REASONS",
           "OK", "HF_POWER", "AT_THE_STOP", "ERROR_GROWTH", "NOT_FINITE", "WATCHDOG_STATE"]
