"""A guarded deployment, in process: the controller moves from the safe gains
to the tuned ones in steps while the watchdog (:mod:`.watchdog`) watches the
loop, and falls back to the last gains that held a whole step when it trips.

The plan (:class:`DeploymentPlan`): ``settle`` [s] on the safe gains, then
``steps`` gain sets geometric between safe and tuned (k_j = k_safe^(1−j/N)·
k_tuned^(j/N), j = 1 … N), each held ``hold`` [s]; the run lasts the plan
(the configured horizon if longer). A step is *held* when it ran its whole
hold without a trip. The watchdog watches from the first step on: the
settling on the safe gains is the machine's state before the deployment
(in a simulation, the start-up transient of SPEC §4's initial state). On
a trip at sample i the gains of the last held step (the row before the one
in effect; the safe ones before any) take effect at sample i + 1, the
watchdog's windows start again, and no later step is taken; a trip on the fallback
gains falls back to the safe gains.

It runs the core's own sample step (:func:`~has_control.core.episode.general_sample_step`)
on the configured plant, so a simulated machine (a second-order spool,
delay, friction, sensors) is deployed to exactly as the tuner scored it.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from has_control.config import with_horizon
from has_control.core.cost import metric_finish
from has_control.core.episode import (
    _A1, _A2, _GENERAL_ROWS, _J, _K1, _K2, _K3, _M2, _MEAN, _PEAK, _X1, _X2, _X3, _X4, EpisodeArrays, _constants,
    general_sample_step, put_trace_row, simulate,
)
from has_control.core.jit import KERNEL, LEAF
from has_control.core.noise import measurement_noise
from has_control.core.params import A1_INIT, A2_INIT, Config
from has_control.core.reference import reference
from has_control.deploy.stepping import (FALLEN, PLAN_STATE, STEP, TRIP2_AT, TRIP2_REASON, TRIP_AT, TRIP_REASON,
                                         TRIP_STEP, plan_switch, plan_watch)
from has_control.deploy.watchdog import REASONS, WATCHDOG_STATE, WatchdogLimits

#: Events of a run: (sample tripped, reason, step at the trip, second trip sample, its reason).
_EVENTS = 5


@dataclass(frozen=True)
class DeploymentPlan:
    """safe and tuned gains (k1, k2, k3) [1/s]; steps; settle and hold [s]."""

    safe: tuple[float, float, float]
    tuned: tuple[float, float, float]
    steps: int = 4
    settle: float = 1.0
    hold: float = 1.0

    def check(self) -> None:
        for name in ("safe", "tuned"):
            k = getattr(self, name)
            if len(k) != 3 or not all(math.isfinite(v) and v > 0.0 for v in k):
                raise ValueError(f"{name} gains {k!r}: expected three positive numbers [1/s]")
        if not (1 <= self.steps <= 100):
            raise ValueError(f"steps = {self.steps!r}: must be 1..100")
        for name in ("settle", "hold"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 < v <= 3600.0):
                raise ValueError(f"{name} = {v!r} s: must be in (0, 3600]")

    def schedule(self) -> np.ndarray:
        """(steps + 1, 3): the safe gains, then each step's."""
        safe, tuned = np.log(self.safe), np.log(self.tuned)
        f = np.arange(self.steps + 1)[:, None] / self.steps
        return np.exp(safe * (1.0 - f) + tuned * f)

    def switches(self, dt: float) -> np.ndarray:
        """The sample at which each row of :meth:`schedule` takes effect."""
        first = int(round(self.settle / dt))
        per = int(round(self.hold / dt))
        return np.array([0] + [first + j * per for j in range(self.steps)], dtype=np.int64)

    def duration(self) -> float:
        return self.settle + self.steps * self.hold


@dataclass(frozen=True)
class DeploymentResult:
    """What the guarded run did: ``J`` of the whole run and of the safe gains
    alone over the same run; ``tripped_at`` [s] (None: no trip), ``reason``,
    ``step`` (the step that tripped, 1 … N), ``fallback`` gains; the gains in
    effect at the end; ``detected_after`` [s] from the start of the step that
    tripped; ``tuned_J``: the tuned gains alone on the machine (what deploying
    them at once would have cost); ``predicted_J``: what the tuner promised
    (None if not given) and whether the measured J of the tuned gains is more
    than twice it."""

    plan: DeploymentPlan
    J: float
    safe_J: float
    tuned_J: float
    final_gains: tuple[float, float, float]
    tripped_at: float | None
    reason: str | None
    step: int | None
    fallback: tuple[float, float, float] | None
    detected_after: float | None
    second_trip_at: float | None
    predicted_J: float | None = None
    trace: np.ndarray | None = field(default=None, repr=False)

    @property
    def gap(self) -> float | None:
        """J of the tuned gains on the machine (a whole run on them, as the tuner scored
        its prediction) over the predicted one (when predicted)."""
        if self.predicted_J is None or not self.predicted_J > 0.0:
            return None
        return self.tuned_J / self.predicted_J

    def lines(self) -> list[str]:
        out = [f"deployed in {self.plan.steps} steps of {self.plan.hold:g} s after {self.plan.settle:g} s on the safe "
               f"gains: J = {self.J:.6e} (safe gains alone {self.safe_J:.6e}, {self.J / self.safe_J:.3g}x; the tuned "
               f"gains at once {self.tuned_J:.6e})"]
        if self.tripped_at is None:
            out.append(f"watchdog: no trip; final gains ({', '.join(f'{k:.2f}' for k in self.final_gains)})")
        else:
            out.append(f"watchdog: TRIPPED at {self.tripped_at:.4f} s on step {self.step} ({self.reason}), "
                       f"{self.detected_after * 1e3:.1f} ms into the step; fell back to "
                       f"({', '.join(f'{k:.2f}' for k in self.fallback)})"
                       + (f"; tripped again at {self.second_trip_at:.4f} s: safe gains" if self.second_trip_at else ""))
        g = self.gap
        if g is not None:
            out.append(f"measured against predicted J: {g:.3g}x ({gap_words(g)}; predicted {self.predicted_J:.6e})")
        return out

    def as_json(self) -> dict:
        f = lambda v: v if v is None or math.isfinite(v) else None  # noqa: E731
        return {"J": f(self.J), "safe_J": f(self.safe_J), "tuned_J": f(self.tuned_J),
                "final_gains": list(self.final_gains), "tripped": self.tripped_at is not None,
                "tripped_at": self.tripped_at, "reason": self.reason, "step": self.step,
                "fallback": list(self.fallback) if self.fallback else None,
                "detected_after": self.detected_after, "second_trip_at": self.second_trip_at,
                "predicted_J": self.predicted_J, "gap": f(self.gap) if self.gap is not None else None,
                "gap_over_2x": bool(self.gap is not None and self.gap > 2.0),
                "plan": dataclasses.asdict(self.plan)}


def gap_words(gap: float) -> str:
    """How a measured-over-predicted J is reported: a gap over 2x is flagged
    (the model promised far better than the machine gives); a measured J
    below the predicted is said as such, not as "within 2x"."""
    if gap > 2.0:
        return "GAP over 2x"
    return "within 2x" if gap >= 0.5 else "below the prediction, no gap over 2x"


@njit(**KERNEL)
def _guarded(schedule, switches, lim, ap, pp, cp, rp, sp, seed, ep, x0, trace, events):
    """The guarded run (see the module); fills ``trace`` rows and ``events``;
    returns (J, e_max, e_μ, e_σ, samples, diverged, index of the final gains' row or −1 for the fallback)."""
    ap, pp, cp, sp, noisy, ep, dt, n, lo, hi, y_limit = _constants(ap, pp, cp, sp, ep)
    s = np.zeros((_GENERAL_ROWS, 1))
    s[_X1, 0], s[_X2, 0], s[_X3, 0], s[_X4, 0] = x0[0], x0[1], x0[2], x0[3]
    s[_A1, 0] = cp[A1_INIT]
    s[_A2, 0] = cp[A2_INIT]
    w = np.zeros(WATCHDOG_STATE)
    d = np.empty(PLAN_STATE)
    d[:] = -1.0
    d[STEP] = d[FALLEN] = 0.0
    count = 0.0
    for i in range(n):
        row = plan_switch(d, i, switches, w)
        if row >= 0:
            s[_K1, 0], s[_K2, 0], s[_K3, 0] = schedule[row, 0], schedule[row, 1], schedule[row, 2]
        r0, r1, r2, r3 = reference(rp, i * dt)
        n1, n2, n3, n4 = measurement_noise(sp, seed, i) if noisy else (0.0, 0.0, 0.0, 0.0)
        in_window = lo <= i <= hi
        if in_window:
            count += 1.0
        x1, x2, x3, x4, a1_hat, a2_hat = s[_X1, 0], s[_X2, 0], s[_X3, 0], s[_X4, 0], s[_A1, 0], s[_A2, 0]
        k1, k2, k3 = s[_K1, 0], s[_K2, 0], s[_K3, 0]
        bad, u, e1, e2, e3 = general_sample_step(s, 0, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count,
                                                 in_window, ap, pp, cp, sp, ep, dt, y_limit)
        if trace.shape[0] > 0:
            put_trace_row(trace[i], i * dt, r0, x1, x2, x3, x4, u, e1, e2, e3, a1_hat, a2_hat)
            trace[i, 12], trace[i, 13], trace[i, 14] = k1, k2, k3
        if bad:
            _events(d, events)
            return math.inf, math.inf, math.inf, math.inf, i + 1, True, -1
        back = plan_watch(d, w, i, u, e1, lim)
        if back >= 0:
            s[_K1, 0], s[_K2, 0], s[_K3, 0] = schedule[back, 0], schedule[back, 1], schedule[back, 2]
    _events(d, events)
    e_max, e_mu, e_sigma = metric_finish(count, s[_MEAN, 0], s[_M2, 0], s[_PEAK, 0])
    return s[_J, 0], e_max, e_mu, e_sigma, n, False, int(d[STEP]) - 1 if d[FALLEN] == 0.0 else -1


@njit(**LEAF)
def _events(d, events):
    """(first trip's sample, reason, step, second trip's sample, reason) of the plan's state."""
    events[0], events[1], events[2] = d[TRIP_AT], d[TRIP_REASON], d[TRIP_STEP]
    events[3], events[4] = d[TRIP2_AT], d[TRIP2_REASON]


def deploy_in_process(cfg: Config, plan: DeploymentPlan, limits: WatchdogLimits | None = None,
                      predicted_J: float | None = None, keep_trace: bool = False) -> DeploymentResult:
    """Deploy ``plan`` on the machine ``cfg`` simulates, guarded by ``limits``
    (default: :class:`WatchdogLimits` with the plant's valve limit)."""
    plan.check()
    limits = limits or WatchdogLimits(valve_limit=cfg.plant.valve_limit)
    limits.check()
    if cfg.episode.horizon < plan.duration():
        cfg = with_horizon(cfg, plan.duration())
    arr = EpisodeArrays.from_config(cfg)
    dt = cfg.episode.step
    schedule = np.ascontiguousarray(plan.schedule())
    switches = plan.switches(dt)
    trace = np.zeros((cfg.episode.samples if keep_trace else 0, 15))
    events = np.zeros(_EVENTS)
    ap, pp, cp, rp, sp, seed, ep, x0 = arr.kernel_args()
    j, _, _, _, n, bad, last = _guarded(schedule, switches, limits.as_array(dt), ap, pp, cp, rp, sp, seed, ep, x0,
                                        trace, events)
    safe_J = simulate(cfg, plan.safe).score.J
    tuned_J = simulate(cfg, plan.tuned).score.J
    tripped = events[0] >= 0
    step = int(events[2]) if tripped else None
    fallback = None
    if tripped:
        fallback = tuple(float(v) for v in _fallback_row(schedule, switches, int(events[0])))
    final = fallback if tripped else tuple(float(v) for v in schedule[last])
    if events[3] >= 0:
        final = tuple(float(v) for v in schedule[0])
    detected = (events[0] - switches[step]) * dt if tripped else None
    return DeploymentResult(plan, float(j), float(safe_J), float(tuned_J), final,
                            float(events[0] * dt) if tripped else None,
                            REASONS.get(int(events[1])) if tripped else None, step, fallback, detected,
                            float(events[3] * dt) if events[3] >= 0 else None, predicted_J,
                            trace[:n] if keep_trace else None)


def _fallback_row(schedule, switches, at: int) -> np.ndarray:
    """The gains the kernel fell back to at sample ``at``: the last row that held a whole step."""
    started = int(np.searchsorted(switches, at, side="right")) - 1
    return schedule[max(started - 1, 0)]


__all__ = ["DeploymentPlan", "DeploymentResult", "deploy_in_process"]
