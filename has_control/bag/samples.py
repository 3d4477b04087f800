"""The sample columns every recorded run has: state, command and reference on the sample grid."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RunSamples:
    """A recorded run, one row per sample: what :mod:`has_control.bag.score`
    (a strict lock-step run) and :mod:`has_control.bag.series` (any run,
    NaN where nothing was recorded) read back from a bag."""

    t: np.ndarray          # [s]
    y: np.ndarray          # [m]
    ydot: np.ndarray       # [m/s]
    p1: np.ndarray         # [Pa]
    p2: np.ndarray         # [Pa]
    u: np.ndarray          # [m]
    x1d: np.ndarray        # [m]

    @property
    def e1(self) -> np.ndarray:
        """e1 = x1d − y [m] (SPEC §3)."""
        return self.x1d - self.y

    def __getitem__(self, column: str) -> np.ndarray:
        """Trace-style columns: t, x1d, y, ydot, P1, P2, u, e1."""
        if column == "e1":
            return self.e1
        return {"t": self.t, "x1d": self.x1d, "y": self.y, "ydot": self.ydot, "P1": self.p1,
                "P2": self.p2, "u": self.u}[column]
