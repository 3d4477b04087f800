"""Paced lock-step: the real-time timing policy of the plant's loop.

Kept apart from :class:`~has_control.nodes.plant_node.PlantNode` as
ros2_control keeps the update loop's timing apart from the hardware. Sample
i is due at t0 + i·Δt of wall time. The loop, on the thread that owns the
executor (rclpy's EventsExecutor cannot be spun from another thread while a
Python thread paces), does for every sample:

0. start-up: the first state is published at once and its command awaited
   up to the plant's ``first_answer_timeout()`` (the first answer pays one-time
   costs, and a controller just discovered may not yet have discovered us);
1. wait until it is due (sleep in the executor, serving its events, until
   shortly before; then spin on the clock);
2. write: publish state i;
3. read: spin the executor until command i arrives or the sample's deadline
   t0 + (i+1)·Δt passes;
4. update: step the plant with command i; without it (a *miss*) hold the last
   command, and after ``failsafe_samples`` consecutive misses centre the
   valve (u = 0, a *fail-safe sample*), warn once, and recover when commands
   return.

When every command arrives in time the run is the lock-step run, bit for bit.
Simulation time never runs ahead of wall time. A sample that starts more
than one period late is an *overrun*: the schedule is re-based on it (t0
moves), so one stall does not make every later sample late, and a loop that
cannot keep up runs as fast as it can; its real-time factor says how fast.

Lateness is how long after its due time a state was published [µs]; it is
kept in a 1 µs histogram (bounded memory, exact percentiles to 1 µs).
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


@dataclass
class LoopStats:
    """What a paced run did (all counts in samples)."""

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


def run_paced(executor, plant, *, priority: int = 0,
              on_second: Callable[[LoopStats], None] | None = None) -> LoopStats:
    """Run ``plant``'s episode paced to wall time (see the module docstring).

    ``executor`` serves the plant (and, composed in this process, the
    controller); ``on_second`` is called about once a second of wall time
    with the stats so far (diagnostics, progress).
    """
    period = plant.step_ns
    stats = LoopStats(period)
    collecting = gc.isenabled()
    gc.disable()                                         # no collector pause inside a sample
    before = set_realtime_priority(priority)
    if priority > 0 and before is None:
        plant.get_logger().warning(f"realtime_priority {priority}: SCHED_FIFO not permitted; "
                                   "running with normal scheduling")
    if on_second is not None:
        on_second(stats)                                 # warm: the first report pays one-time costs
    clock = time.perf_counter_ns
    hist = stats.late_us
    failsafe_after = plant.failsafe_samples
    in_a_row = 0
    hold = plant.command_u if plant.command_sample >= 0 else 0.0
    start = plant.sample
    t0 = first = last = clock()
    next_report = t0 + 1_000_000_000
    try:
        while not plant.finished:
            i = plant.sample
            due = t0 + (i - start) * period
            now = clock()
            if due - now > SPIN_NS:
                executor.spin_once(timeout_sec=(due - now - SPIN_NS) / 1e9)
                continue                                 # serve what woke us, then wait again
            while now < due:
                now = clock()
            late = now - due
            if late > period:                            # overrun: re-base the schedule here
                stats.overruns += 1
                t0 = now - (i - start) * period
            hist[min(late // 1000, LATE_BINS_US)] += 1
            if late > stats.late_max_ns:
                stats.late_max_ns = late
            plant.publish_state()
            if stats.samples == 0:
                first = now
            last = now
            deadline = t0 + (i - start + 1) * period
            if stats.samples == 0:                       # start-up: the first answer may take longer
                deadline = now + int(plant.first_answer_timeout() * 1e9)
            while plant.command_sample != i:
                left = deadline - clock()
                if left <= 0:
                    break
                executor.spin_once(timeout_sec=left / 1e9)
            if plant.command_sample == i:
                u = hold = plant.command_u
                if in_a_row > failsafe_after:
                    plant.commands_back()
                in_a_row = 0
            else:
                if stats.missed < MISSES_KEPT:
                    stats.missed_at.append(i)
                stats.missed += 1
                _extend(stats.missed_spans, i)
                in_a_row += 1
                if in_a_row > failsafe_after:
                    stats.failsafe += 1
                    _extend(stats.failsafe_spans, i)
                    plant.failsafe(in_a_row)
                    u = 0.0
                else:
                    u = hold
            plant.step(u, answered=not in_a_row)
            stats.samples += 1
            stats.sim_ns = (stats.samples - 1) * period
            stats.wall_ns = last - first
            if on_second is not None and now >= next_report and \
                    t0 + (i - start + 1) * period - clock() > REPORT_SLACK_NS:
                next_report = now + 1_000_000_000
                on_second(stats)
    finally:
        restore_priority(before)
        if collecting:
            gc.enable()
    return stats
