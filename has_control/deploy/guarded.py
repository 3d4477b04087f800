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

With ``measure`` > 0 the plan ends with the comparison of
:mod:`.stepping`: after the last step's hold, ``measure`` [s] on the safe
gains, then ``measure`` on the gains that held, each window's J measured, and
the held gains are kept only when they measured below the safe gains' J by
more than ``margin``; else the deployment ends on the safe gains. The
documented path sets ``measure`` to one period of the reference
(:func:`reference_period`), so both windows cover the same segment of it.

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
    _ring_read, _ring_write, general_sample_step, put_trace_row, simulate,
)
from has_control.core.jit import KERNEL, LEAF
from has_control.core.noise import measurement_noise
from has_control.core.params import A1_INIT, A2_INIT, Config
from has_control.core.reference import reference
from has_control.deploy.stepping import (ROW, TRIP2_AT, TRIP2_REASON, TRIP_AT, TRIP_REASON, TRIP_STEP, Comparison,
                                         comparison_of, plan_cost, plan_state, plan_switch, plan_watch)
from has_control.deploy.watchdog import REASONS, WATCHDOG_STATE, WatchdogLimits

#: Events of a run: (sample tripped, reason, step at the trip, second trip sample, its reason).
_EVENTS = 5


@dataclass(frozen=True)
class DeploymentPlan:
    """safe and tuned gains (k1, k2, k3) [1/s]; steps; settle and hold [s];
    measure [s]: each window of the final comparison (0: none), margin [-]
    (default 0.10: twice the spread one period's J shows on a noisy machine, docs/deploy.md):
    how far below the safe gains' J the held gains' must measure to be kept."""

    safe: tuple[float, float, float]
    tuned: tuple[float, float, float]
    steps: int = 4
    settle: float = 1.0
    hold: float = 1.0
    measure: float = 0.0
    margin: float = 0.10

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
        if not (math.isfinite(self.measure) and 0.0 <= self.measure <= 3600.0):
            raise ValueError(f"measure = {self.measure!r} s: must be in [0, 3600] (0: no comparison)")
        if not (math.isfinite(self.margin) and 0.0 <= self.margin < 1.0):
            raise ValueError(f"margin = {self.margin!r}: must be in [0, 1)")

    def schedule(self) -> np.ndarray:
        """(steps + 1, 3): the safe gains, then each step's (geometric), the
        first and last rows the safe and tuned gains exactly as given (exp of
        log is not: 150 came back as 149.99999999999997, and a fallback is to
        the user's own numbers)."""
        safe, tuned = np.log(self.safe), np.log(self.tuned)
        f = np.arange(self.steps + 1)[:, None] / self.steps
        rows = np.exp(safe * (1.0 - f) + tuned * f)
        rows[0], rows[-1] = self.safe, self.tuned
        return rows

    def switches(self, dt: float) -> np.ndarray:
        """The sample at which each row of :meth:`schedule` takes effect."""
        first = int(round(self.settle / dt))
        per = int(round(self.hold / dt))
        return np.array([0] + [first + j * per for j in range(self.steps)], dtype=np.int64)

    def compare(self, dt: float) -> tuple[int, int, float] | None:
        """(V, W, margin) of the comparison (:func:`~has_control.deploy.stepping.plan_state`): V the sample
        after the last step's hold, W the window [samples]; None without one."""
        if self.measure <= 0.0:
            return None
        last = self.switches(dt)[-1]
        return int(last + int(round(self.hold / dt))), max(int(round(self.measure / dt)), 1), float(self.margin)

    def duration(self) -> float:
        return self.settle + self.steps * self.hold + 2.0 * self.measure


def reference_period(cfg: Config) -> float | None:
    """The configured reference's period [s] when it repeats (a sine: 2π/ω), else None."""
    r = cfg.reference
    if r.kind == "sine" and r.omega > 0.0:
        return 2.0 * math.pi / r.omega
    return None


@dataclass(frozen=True)
class DeploymentResult:
    """What the guarded run did: ``J`` of the whole run and of the safe gains
    alone over the same run; ``tripped_at`` [s] (None: no trip), ``reason``,
    ``step`` (the step that tripped, 1 … N), ``fallback`` gains; the gains in
    effect at the end; ``detected_after`` [s] from the start of the step that
    tripped; ``tuned_J``: the tuned gains alone on the machine (what deploying
    them at once would have cost); ``predicted_J``: what the tuner promised
    (None if not given) and whether the measured J of the tuned gains is more
    than twice it; ``comparison``: what the final comparison measured and
    kept (None: the plan had none)."""

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
    comparison: Comparison | None = None
    hf_limit: float | None = None          # the watchdog's command-power limit in effect [m] (None: as configured)

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
        if self.hf_limit is not None:
            out.append(f"watchdog: its command-power limit raised to {self.hf_limit * 1e3:.3g} mm, three times the "
                       "safe gains' own above the corner as the settling ended")
        if self.tripped_at is None:
            out.append(f"watchdog: no trip; final gains ({', '.join(f'{k:.2f}' for k in self.final_gains)})")
        else:
            out.append(f"watchdog: TRIPPED at {self.tripped_at:.4f} s on step {self.step} ({self.reason}), "
                       f"{self.detected_after * 1e3:.1f} ms into the step; fell back to "
                       f"({', '.join(f'{k:.2f}' for k in self.fallback)})"
                       + (f"; tripped again at {self.second_trip_at:.4f} s: safe gains" if self.second_trip_at else ""))
        if self.comparison is not None:
            out.append(self.comparison.line(self.plan.steps))
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
                "comparison": self.comparison.as_json() if self.comparison is not None else None,
                "hf_limit_raised_to": self.hf_limit, "plan": dataclasses.asdict(self.plan)}


def gap_words(gap: float) -> str:
    """How a measured-over-predicted J is reported: a gap over 2x is flagged
    (the model promised far better than the machine gives); a measured J
    below the predicted is said as such, not as "within 2x"."""
    if gap > 2.0:
        return "GAP over 2x"
    return "within 2x" if gap >= 0.5 else "below the prediction, no gap over 2x"


@njit(**KERNEL)
def _guarded(schedule, switches, lim, d, ap, pp, cp, rp, sp, seed, ep, x0, trace, events):
    """The guarded run (see the module) on the plan's state ``d``; fills ``trace`` rows and ``events``;
    returns (J, e_max, e_μ, e_σ, samples, diverged)."""
    ep_array = ep
    ap, pp, cp, sp, noisy, ep, dt, n, lo, hi, y_limit = _constants(ap, pp, cp, sp, ep)
    s = np.zeros((_GENERAL_ROWS, 1))
    s[_X1, 0], s[_X2, 0], s[_X3, 0], s[_X4, 0] = x0[0], x0[1], x0[2], x0[3]
    s[_A1, 0] = cp[A1_INIT]
    s[_A2, 0] = cp[A2_INIT]
    w = np.zeros(WATCHDOG_STATE)
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
        _ring_read(s, i, pp)                 # the delay's ring, as the episode kernel keeps it
        bad, u, e1, e2, e3 = general_sample_step(s, 0, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count,
                                                 in_window, ap, pp, cp, sp, ep, dt, y_limit)
        _ring_write(s, i)
        if trace.shape[0] > 0:
            put_trace_row(trace[i], i * dt, r0, x1, x2, x3, x4, u, e1, e2, e3, a1_hat, a2_hat)
            trace[i, 12], trace[i, 13], trace[i, 14] = k1, k2, k3
        if bad:
            _events(d, events)
            return math.inf, math.inf, math.inf, math.inf, i + 1, True
        back = plan_watch(d, w, i, u, e1, lim)
        plan_cost(d, u, e1, ep_array)
        if back >= 0:
            s[_K1, 0], s[_K2, 0], s[_K3, 0] = schedule[back, 0], schedule[back, 1], schedule[back, 2]
    _events(d, events)
    e_max, e_mu, e_sigma = metric_finish(count, s[_MEAN, 0], s[_M2, 0], s[_PEAK, 0])
    return s[_J, 0], e_max, e_mu, e_sigma, n, False


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
    d = plan_state(plan.compare(dt))
    lim = limits.as_array(dt)
    j, _, _, _, n, bad = _guarded(schedule, switches, lim, d, ap, pp, cp, rp, sp, seed, ep, x0, trace, events)
    safe_J = simulate(cfg, plan.safe).score.J
    tuned_J = simulate(cfg, plan.tuned).score.J
    tripped = events[0] >= 0
    step = int(events[2]) if tripped else None
    fallback = None
    if tripped:
        cmp = plan.compare(dt)
        during = cmp is not None and events[0] >= cmp[0]            # a trip in the comparison: the safe gains
        fallback = tuple(float(v) for v in (schedule[0] if during else
                                            _fallback_row(schedule, switches, int(events[0]))))
    final = tuple(float(v) for v in schedule[int(d[ROW])])
    detected = (events[0] - switches[step]) * dt if tripped else None
    return DeploymentResult(plan, float(j), float(safe_J), float(tuned_J), final,
                            float(events[0] * dt) if tripped else None,
                            REASONS.get(int(events[1])) if tripped else None, step, fallback, detected,
                            float(events[3] * dt) if events[3] >= 0 else None, predicted_J,
                            trace[:n] if keep_trace else None, comparison_of(d, dt),
                            float(lim[2]) if lim[2] > limits.hf_rms else None)


def _fallback_row(schedule, switches, at: int) -> np.ndarray:
    """The gains the kernel fell back to at sample ``at``: the last row that held a whole step."""
    started = int(np.searchsorted(switches, at, side="right")) - 1
    return schedule[max(started - 1, 0)]


__all__ = ["DeploymentPlan", "DeploymentResult", "deploy_in_process", "reference_period"]
