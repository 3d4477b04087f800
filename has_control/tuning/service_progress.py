"""What the tuner node says while a session runs (ROS-free): the observer of each
iteration and the estimate logged before a graph tuning.

:class:`Progress` turns each iteration of the optimiser into a status line, a
row of :data:`has_control.wire.topics.PROGRESS_COLUMNS` (the node publishes it
on ``~/progress``) and, every ``every``-th iteration and the last, a log line;
:func:`graph_estimate` says how long a graph tuning takes and what its bags weigh.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

#: Bytes a recorded episode takes per sample (state, command, clock, reference, internals, each with
#: its MCAP record header): the estimate logged before a graph tuning.
BAG_BYTES_PER_SAMPLE = 246
#: Lock-step rates [samples/s per lane] between which a graph tuning's time is estimated.
GRAPH_RATES = (20_000.0, 1_000.0)


class Progress:
    """The session's observer (``on_iteration``): for each iteration ``status(line)``,
    ``publish(row)`` with the row [iteration, best J, k1, k2, k3 [1/s], evaluations,
    elapsed [s], ETA [s]], ``log(line)`` every ``every``-th iteration and the last, then
    ``check()`` (which raises to stop the session, e.g. on a cancel)."""

    def __init__(self, every: int, status: Callable[[str], None], publish: Callable[[list], None],
                 log: Callable[[str], None], check: Callable[[], None] = lambda: None):
        self.every, self.t0 = max(1, every), time.perf_counter()
        self.status, self.publish, self.log, self.check = status, publish, log, check

    def __call__(self, sw) -> None:
        k = sw.best_x
        elapsed = time.perf_counter() - self.t0
        progress = sw.progress()                   # the share of the budget used, 0..1
        eta = elapsed / progress * (1.0 - progress) if progress > 0 else math.inf
        self.status(f"running: {sw.name} iteration {sw.iteration} ({100 * progress:.0f} %), "
                    f"best J = {sw.best_f:.6e}, ETA {eta:.0f} s")
        self.publish([float(sw.iteration), sw.best_f, *map(float, k), float(sw.evaluations), elapsed, eta])
        if sw.iteration % self.every == 0 or sw.done:
            self.log(f"{sw.name} iteration {sw.iteration} ({100 * progress:.0f} %): best J = {sw.best_f:.6e} "
                     f"at k = ({k[0]:.2f}, {k[1]:.2f}, {k[2]:.2f}), {sw.evaluations} evaluations, ETA {eta:.0f} s")
        self.check()


def graph_estimate(episodes_count: int, samples: int, lanes: int, keep: bool, episodes: Path) -> str:
    """Before a graph tuning: how many episodes, how long (from a lock-step rate of
    1 000–20 000 samples/s per lane, :data:`GRAPH_RATES`), and what the bags take."""
    per_bag = samples * BAG_BYTES_PER_SAMPLE
    fast, slow = (episodes_count * samples / lanes / rate for rate in GRAPH_RATES)
    return (f"graph tuning: {episodes_count} episodes of {samples} samples over {lanes} lane(s), about "
            f"{duration(fast)} to {duration(slow)}; each episode's bag ~{per_bag / 1e6:.1f} MB, "
            + (f"kept under {episodes} ({episodes_count * per_bag / 1e9:.2f} GB in all)" if keep
               else "scored then deleted (keep_episodes:=true keeps them)") + "; ~/progress shows the ETA")


def duration(seconds: float) -> str:
    """A wall time in the unit that reads best: s below 2 min, min below 2 h, else h."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"
