"""Progress on a terminal: one self-rewriting line on stderr, silent when piped."""
from __future__ import annotations

import sys
import time


class StatusLine:
    """One self-rewriting status line on a terminal (stderr); silent when piped."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty()
        self.used = False

    def show(self, text: str) -> None:
        if self.enabled:
            self.stream.write(f"\r{text} ")
            self.stream.flush()
            self.used = True

    def close(self) -> None:
        if self.used:
            self.stream.write("\n")


class Progress(StatusLine):
    """A tuning run's progress bar on a terminal: evaluations, best J, the rate
    and the time left, both measured from the first update (which has no rate yet)."""

    def __init__(self, stream=None):
        super().__init__(stream)
        self.first = None           # (time, evaluations, progress) at the first update

    def __call__(self, swarm) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        p = swarm.progress()
        if self.first is None:
            self.first = (now, swarm.evaluations, p)
        t0, n0, p0 = self.first
        elapsed = now - t0
        rate = f"{(swarm.evaluations - n0) / elapsed:,.0f} eval/s" if elapsed > 0 and swarm.evaluations > n0 else \
            "- eval/s"
        eta = f"ETA {elapsed * (1.0 - p) / (p - p0):.0f} s" if p > p0 and elapsed > 0 else "ETA -"
        filled = int(30 * p)
        self.show(f"{swarm.name} seed {swarm.seed} [{'#' * filled}{'.' * (30 - filled)}] "
                  f"{swarm.evaluations} evaluations  best J {swarm.gbest_f:.6e}  {rate}  {eta}")
