"""One sample loop, two timing policies (as ros2_control has one read → update →
write loop with a timing policy).

:func:`run_loop` runs a plant's episode on the thread that owns the events
(``spin_once``: an rclpy executor's, or a fake's in tests) under a schedule:

* :class:`LockStep`: as fast as the controller answers. The state of sample i
  is published, command i advances the plant (:meth:`LockStep.answer`, called by
  the plant when it arrives), and the next state is published. A state
  unanswered after a quarter of ``timeout`` is sent again each quarter (a
  controller that has just matched may have missed it); after ``timeout`` [s of
  wall time] the fail-safe runs the sample with the valve centred
  (:meth:`LockStep.tick`, the watchdog). The first sample of a run waits up to
  the plant's ``first_answer_timeout()`` instead.
* :class:`Paced`: sample i is due at t0 + i·Δt of wall time. Each sample: wait
  until due (serving events until shortly before, then spinning on the clock),
  publish state i, serve events until command i arrives or the deadline
  t0 + (i+1)·Δt passes, step with it; without it (a *miss*) hold the last
  command, and after ``failsafe_samples`` consecutive misses centre the valve
  (a *fail-safe sample*) until commands return. When every command arrives in
  time the run is the lock-step run, bit for bit. A sample that starts more
  than a period late is an *overrun*: the schedule is re-based on it (t0
  moves), so one stall does not make every later sample late. The first state
  waits up to ``first_answer_timeout()`` for its answer.

Lateness is how long after its due time a state was published [µs], kept in a
1 µs histogram (bounded memory, exact percentiles to 1 µs).

The plant side of the loop (:class:`~has_control.loop.plant.PlantProcess`, or
any object with the same members: ``step_ns``, ``sample``, ``finished``,
``command_sample``, ``command_u``, ``publish_state()``, ``first_answer_timeout()``,
``step(u, answered)``, ``failsafe(missing)``, ``commands_back()``, ``logger``).
"""
from __future__ import annotations

import gc
import os
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

#: Lateness histogram: 1 µs bins up to this many µs; later samples share the last bin.
LATE_BINS_US = 10_000
#: Sleep in the executor until this long before a sample is due, then spin [ns].
SPIN_NS = 150_000
#: Missed samples whose index is kept (for reports and tests).
MISSES_KEPT = 1000
#: The once-a-second report waits for a sample that leaves at least this much slack [ns].
REPORT_SLACK_NS = 200_000
#: Lock-step: events served between two checks (``check``, the watchdog, the report).
BURST = 256


@dataclass
class LoopStats:
    """What a run did (all counts in samples)."""

    period_ns: int
    samples: int = 0
    missed: int = 0                  # commands that did not arrive by their deadline
    failsafe: int = 0                # samples run with the valve centred
    overruns: int = 0                # samples that started more than a period late
    sim_ns: int = 0                  # simulation time from the first state published to the last
    wall_ns: int = 0                 # wall time over the same span
    late_max_ns: int = 0
    missed_at: list[int] = field(default_factory=list)   # the first MISSES_KEPT missed samples
    missed_spans: list[list[int]] = field(default_factory=list)     # every missed sample, as [first, last] runs
    failsafe_spans: list[list[int]] = field(default_factory=list)   # every fail-safe sample, as [first, last] runs
    late_us: np.ndarray = field(default_factory=lambda: np.zeros(LATE_BINS_US + 1, dtype=np.int64))

    def late_percentile(self, q: float) -> float:
        """Lateness [µs] below which ``q`` % of samples were published."""
        n = int(self.late_us.sum())
        if n == 0:
            return float("nan")
        return float(np.searchsorted(np.cumsum(self.late_us), q / 100.0 * n))

    def as_dict(self) -> dict[str, float]:
        rate = (self.samples - 1) / (self.wall_ns / 1e9) if self.wall_ns else float("nan")
        return {"samples": float(self.samples), "rate_hz": rate, "target_hz": 1e9 / self.period_ns,
                "realtime_factor": self.sim_ns / self.wall_ns if self.wall_ns else float("nan"),
                "missed_samples": float(self.missed), "failsafe_samples": float(self.failsafe),
                "overruns": float(self.overruns), "late_p50_us": self.late_percentile(50),
                "late_p99_us": self.late_percentile(99), "late_max_us": self.late_max_ns / 1e3}


def paced_summary(st: dict[str, float]) -> str:
    """The one line a paced run ends with (``st``: :meth:`LoopStats.as_dict`)."""
    return (f"realtime: {st['rate_hz']:.0f} samples/s, real-time factor {st['realtime_factor']:.4f}, "
            f"{st['missed_samples']:.0f} missed, {st['failsafe_samples']:.0f} fail-safe, lateness p50 "
            f"{st['late_p50_us']:.0f} us, p99 {st['late_p99_us']:.0f} us, max {st['late_max_us']:.0f} us, "
            f"{st['overruns']:.0f} overruns")


def _extend(spans: list[list[int]], i: int) -> None:
    """Add sample ``i`` to [first, last] runs (a run of misses is one entry, whatever its length)."""
    if spans and spans[-1][1] == i - 1:
        spans[-1][1] = i
    else:
        spans.append([i, i])


def set_realtime_priority(priority: int) -> tuple[int, int] | None:
    """SCHED_FIFO at ``priority`` for the calling thread (as ros2_control asks).
    Returns the previous (policy, priority) to restore, or None if not permitted."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return None
    try:
        before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return before
    except (PermissionError, OSError):
        return None


def restore_priority(before: tuple[int, int] | None) -> None:
    if before is not None:
        os.sched_setscheduler(0, before[0], os.sched_param(before[1]))


class Schedule:
    """A timing policy's settings: ``timeout`` [s of wall time] a lock-step sample
    waits for its command, ``startup_timeout`` [s] the first answer of a run waits
    while a matched controller has not answered, ``failsafe_samples`` paced misses
    in a row before the valve is centred."""

    paced = False

    def __init__(self, timeout: float = 0.5, startup_timeout: float = 5.0, failsafe_samples: int = 10):
        self.timeout, self.startup_timeout, self.failsafe_samples = timeout, startup_timeout, failsafe_samples


class LockStep(Schedule):
    """As fast as the controller answers, with a watchdog: resend each quarter of
    ``timeout`` [s], the fail-safe after it (``startup_timeout`` governs the first
    answer of a run through the plant's ``first_answer_timeout()``)."""

    def answer(self, plant, i: int, u: float) -> None:
        """Command ``i`` [m] arrived (the plant has recorded it): if it is the one
        awaited, advance and publish the next state."""
        if plant.finished or not plant.published or i != plant.sample:
            return                                   # stale or early: not the sample we wait on
        if plant.fail_safe.in_outage:
            plant.commands_back()
        if plant.step(u):
            plant.publish_state()

    def tick(self, plant, now: float) -> None:
        """The watchdog at monotonic time ``now`` [s]: resend, or the fail-safe."""
        if plant.finished or not plant.published:
            return
        waited = now - plant.last_publish
        limit = plant.first_answer_timeout() if plant.sample == plant.first_sample else self.timeout
        if waited > limit:
            plant.failsafe(1)
            if plant.step(0.0, answered=False):
                plant.publish_state()
        elif waited > self.timeout / 4:
            plant.resend()

    def begin(self, plant, stats: LoopStats, now_ns: int) -> None:
        self._start, self._t0, self._fs0 = plant.sample, now_ns, plant.fail_safe.samples
        self._tick = time.monotonic()
        if not plant.published:
            plant.publish_state()

    def sample(self, plant, spin_once, stats: LoopStats, clock) -> None:
        """Serve up to :data:`BURST` events (each answer steps the plant), then the watchdog."""
        wait = min(0.1, self.timeout / 4)
        for _ in range(BURST):
            spin_once(timeout_sec=wait)
            if plant.finished:
                break
        now = time.monotonic()
        if now - self._tick >= self.timeout / 4:
            self._tick = now
            self.tick(plant, now)
        stats.samples = plant.sample - self._start
        stats.sim_ns = stats.samples * plant.step_ns
        stats.wall_ns = clock() - self._t0
        stats.failsafe = plant.fail_safe.samples - self._fs0


class Paced(Schedule):
    """Sample i due at t0 + i·Δt of wall time; a command missing at its deadline is
    a miss (the last one held), ``failsafe_samples`` misses in a row centre the valve."""

    paced = True

    def answer(self, plant, i: int, u: float) -> None:
        """Commands are read by the loop at each sample's deadline."""

    def tick(self, plant, now: float) -> None:
        """No watchdog: the loop keeps the deadlines."""

    def begin(self, plant, stats: LoopStats, now_ns: int) -> None:
        self.in_a_row = 0
        self.hold = plant.command_u if plant.command_sample >= 0 else 0.0
        self.start = plant.sample
        self.t0 = self.first = now_ns

    def sample(self, plant, spin_once, stats: LoopStats, clock) -> None:
        """One paced sample (or, when it is not yet due, one wait in the executor)."""
        period, start = stats.period_ns, self.start
        i = plant.sample
        due = self.t0 + (i - start) * period
        now = clock()
        if due - now > SPIN_NS:
            spin_once(timeout_sec=(due - now - SPIN_NS) / 1e9)
            return                                       # serve what woke us, then wait again
        while now < due:
            now = clock()
        late = now - due
        if late > period:                                # overrun: re-base the schedule here
            stats.overruns += 1
            self.t0 = now - (i - start) * period
        stats.late_us[min(late // 1000, LATE_BINS_US)] += 1
        if late > stats.late_max_ns:
            stats.late_max_ns = late
        plant.publish_state()
        if stats.samples == 0:
            self.first = now
        deadline = self.t0 + (i - start + 1) * period
        if stats.samples == 0:                           # start-up: the first answer may take longer
            deadline = now + int(plant.first_answer_timeout() * 1e9)
        while plant.command_sample != i:
            left = deadline - clock()
            if left <= 0:
                break
            spin_once(timeout_sec=left / 1e9)
        if plant.command_sample == i:
            u = self.hold = plant.command_u
            if self.in_a_row > self.failsafe_samples:
                plant.commands_back()
            self.in_a_row = 0
        else:
            if stats.missed < MISSES_KEPT:
                stats.missed_at.append(i)
            stats.missed += 1
            _extend(stats.missed_spans, i)
            self.in_a_row += 1
            if self.in_a_row > self.failsafe_samples:
                stats.failsafe += 1
                _extend(stats.failsafe_spans, i)
                plant.failsafe(self.in_a_row)
                u = 0.0
            else:
                u = self.hold
        plant.step(u, answered=not self.in_a_row)
        stats.samples += 1
        stats.sim_ns = (stats.samples - 1) * period
        stats.wall_ns = now - self.first

    def report_due(self, stats: LoopStats, now: int, clock) -> bool:
        """A report now leaves the next sample enough slack."""
        return self.t0 + stats.samples * stats.period_ns - clock() > REPORT_SLACK_NS


def schedule_of(mode: str, **settings) -> Schedule:
    """The schedule of ``mode`` ('lockstep' | 'realtime')."""
    return (Paced if mode == "realtime" else LockStep)(**settings)


MODES = ("lockstep", "realtime")


def run_loop(plant, spin_once, schedule, *, priority: int = 0,
             on_second: Callable[[LoopStats], None] | None = None,
             check: Callable[[], None] | None = None) -> LoopStats:
    """Run ``plant``'s episode under ``schedule`` (:class:`LockStep` or :class:`Paced`)
    on this thread, which owns the events ``spin_once(timeout_sec=...)`` serves.

    The collector is off for the run (no pause inside a sample); with ``priority``
    > 0 the thread runs SCHED_FIFO where permitted. ``on_second(stats)`` is called
    about once a second of wall time (diagnostics, progress; in a paced run only
    where the next sample has slack), ``check()`` after every burst of lock-step
    events (e.g. to end the run early by setting ``plant.finished``).
    """
    stats = LoopStats(plant.step_ns)
    collecting = gc.isenabled()
    gc.disable()
    before = set_realtime_priority(priority)
    if priority > 0 and before is None:
        plant.logger.warning(f"realtime_priority {priority}: SCHED_FIFO not permitted; running with normal scheduling")
    if on_second is not None:
        on_second(stats)                                 # warm: the first report pays one-time costs
    clock = time.perf_counter_ns
    schedule.begin(plant, stats, clock())
    next_report = clock() + 1_000_000_000
    paced = schedule.paced
    try:
        while not plant.finished:
            schedule.sample(plant, spin_once, stats, clock)
            if check is not None and not paced:
                check()
            if on_second is not None:
                now = clock()
                if now >= next_report and (not paced or schedule.report_due(stats, now, clock)):
                    next_report = now + 1_000_000_000
                    on_second(stats)
    finally:
        restore_priority(before)
        if collecting:
            gc.enable()
    return stats
