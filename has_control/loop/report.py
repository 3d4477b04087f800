"""What the plant's loop reports once a second (``/diagnostics``), without ROS:
the figures, the few of them said in words, and whether all is well.

Lock-step: the rate since the last report [samples/s], the samples done and
the plant's counts (:meth:`~has_control.loop.plant.PlantProcess.figures`);
well while no fail-safe outage goes on. Paced: the loop's
:class:`~has_control.loop.schedule.LoopStats` (rate, real-time factor, misses,
lateness) with the plant's counts; well at a real-time factor of at least
0.99 without fail-safe samples.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

from has_control.loop.schedule import LoopStats, paced_summary, run_loop

#: The figures the one-line message names (the rest are in the values only).
SHOWN = ("rate_hz", "realtime_factor", "missed_samples", "failsafe_samples", "late_p99_us")


@dataclass(frozen=True)
class Report:
    """One report: ``what`` loop, its ``values`` by name, ``ok`` (else a warning)."""

    what: str
    values: dict[str, float]
    ok: bool

    @property
    def message(self) -> str:
        """The figures of :data:`SHOWN` that the report has, in one line."""
        return ", ".join(f"{k} {v:.6g}" for k, v in self.values.items() if k in SHOWN)


class LoopReports:
    """The reports of ``process`` (a :class:`~has_control.loop.plant.PlantProcess`),
    timed by ``clock`` [s] (monotonic); the last paced figures are kept in ``realtime_stats``."""

    def __init__(self, process, clock: Callable[[], float] = time.monotonic):
        self.process, self.clock = process, clock
        self.last = (clock(), 0)                     # (time [s], samples done) of the last lock-step report
        self.realtime_stats: dict[str, float] = {}

    def lockstep(self) -> Report:
        """The rate since the last report, the samples done, the plant's counts."""
        now, done = self.clock(), self.process.sample
        then, before = self.last
        self.last = (now, done)
        return Report("lock-step loop", {"rate_hz": (done - before) / (now - then), "samples": float(done),
                                         **self.process.figures()}, not self.process.fail_safe.in_outage)

    def paced(self, stats) -> Report:
        """The paced loop's ``stats`` (:class:`~has_control.loop.schedule.LoopStats`) with the plant's counts."""
        st = stats.as_dict()
        figures = self.process.figures()
        st["failsafe_events"] = figures.pop("failsafe_samples")
        st.update(figures)
        self.realtime_stats = st
        return Report("realtime loop", st, st["realtime_factor"] >= 0.99 and not stats.failsafe)


def run_reported(process, spin_once, reports: LoopReports, publish: Callable[[Report], None], *,
                 priority: int = 0, on_second=None, check=None) -> LoopStats:
    """Run ``process``'s episode (:func:`~has_control.loop.schedule.run_loop`) with its
    reports to ``publish``: a paced run once a second and at the end (then its
    summary line to the process's logger; SCHED_FIFO at ``priority`` where
    permitted), a lock-step run at the end (a run shorter than a second has one:
    its watchdog timer reports the others). ``on_second``, ``check``: as run_loop's."""
    if not process.published:
        process.started_at = time.perf_counter()
    paced = process.schedule.paced

    def each_second(stats: LoopStats) -> None:
        if paced:
            publish(reports.paced(stats))
        if on_second is not None:
            on_second(stats)
    stats = run_loop(process, spin_once, process.schedule, priority=priority if paced else 0,
                     on_second=each_second, check=check)
    if paced:
        publish(reports.paced(stats))
        process.logger.info(paced_summary(reports.realtime_stats))
    else:
        publish(reports.lockstep())
    return stats
