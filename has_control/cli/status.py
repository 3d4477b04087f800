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
    """A tuning run's progress bar on a terminal."""

    def __init__(self, stream=None):
        super().__init__(stream)
        self.t0 = None

    def __call__(self, swarm) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        self.t0 = self.t0 or now - 1e-9
        rate = swarm.evaluations / max(now - self.t0, 1e-9)
        filled = int(30 * swarm.progress())
        self.show(f"{swarm.name} seed {swarm.seed} [{'#' * filled}{'.' * (30 - filled)}] "
                  f"{swarm.evaluations} evaluations  best J {swarm.gbest_f:.6e}  {rate:,.0f} eval/s")
