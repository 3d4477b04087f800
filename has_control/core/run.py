"""One run's time series: the one shape every producer gives and every reader takes.

:func:`~has_control.core.episode.simulate` (a :class:`~has_control.core.episode.Trace`,
a Run with its score and gains), the node stack
(:func:`~has_control.nodes.stack.run_stack`), the bag readers
(:func:`~has_control.bag.score.recorded_run`, :func:`~has_control.bag.series.run_series`)
produce a :class:`Run`; the run figure (:mod:`has_control.plots.run_figure`) draws one.
A run is one row per sample, the columns of :class:`Col`; NaN where a
source has nothing for a sample (a bag without the controller's internals,
a state the controller did not answer).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class Col(IntEnum):
    """The columns of a run, in order, by name: ``run.data[:, Col.e1]``.
    Units: t [s], x1d and y [m], ydot [m/s], P1 and P2 [Pa], u [m], e1 [m],
    e2 [m/s], e3 [N], a1_hat [N·s/m], a2_hat [m³/(s·Pa)]."""

    t = 0
    x1d = 1
    y = 2
    ydot = 3
    P1 = 4
    P2 = 5
    u = 6
    e1 = 7
    e2 = 8
    e3 = 9
    a1_hat = 10
    a2_hat = 11


TRACE_COLUMNS = tuple(c.name for c in Col)
#: The unit of each column, in ASCII (a CSV header's: ``simulate --trace``).
TRACE_UNITS = ("s", "m", "m", "m/s", "Pa", "Pa", "m", "m", "m/s", "N", "N*s/m", "m^3/(s*Pa)")


@dataclass(frozen=True)
class Run:
    """One run, one row per sample: ``data`` is (samples, len(Col)), columns
    :class:`Col` (SI units, see there). t [s] = sample · Δt; e1 = x1d − y [m]
    (SPEC §3). The named properties are views of ``data``'s columns."""

    data: np.ndarray

    @classmethod
    def of(cls, t, x1d, y, ydot, p1, p2, u, *, a1_hat=None, a2_hat=None, e2=None, e3=None, **more):
        """A run from its columns (arrays of one length); e1 = x1d − y; the
        controller's columns not given are NaN. ``more``: a subclass's fields."""
        data = np.full((len(t), len(Col)), np.nan)
        for col, x in ((Col.t, t), (Col.x1d, x1d), (Col.y, y), (Col.ydot, ydot), (Col.P1, p1), (Col.P2, p2),
                       (Col.u, u), (Col.e2, e2), (Col.e3, e3), (Col.a1_hat, a1_hat), (Col.a2_hat, a2_hat)):
            if x is not None:
                data[:, col] = x
        data[:, Col.e1] = data[:, Col.x1d] - data[:, Col.y]
        return cls(data, **more)

    def __getitem__(self, column: str) -> np.ndarray:
        """The column named ``column`` (a :class:`Col` name: t, x1d, y, ydot, P1, P2, u, e1, …)."""
        return self.data[:, Col[column]]

    def __len__(self) -> int:
        return len(self.data)

    t = property(lambda self: self.data[:, Col.t], doc="time [s]")
    x1d = property(lambda self: self.data[:, Col.x1d], doc="reference x1d [m]")
    y = property(lambda self: self.data[:, Col.y], doc="position y [m]")
    ydot = property(lambda self: self.data[:, Col.ydot], doc="velocity ẏ [m/s]")
    p1 = property(lambda self: self.data[:, Col.P1], doc="chamber pressure P1 [Pa]")
    p2 = property(lambda self: self.data[:, Col.P2], doc="chamber pressure P2 [Pa]")
    u = property(lambda self: self.data[:, Col.u], doc="valve command u [m]")
    e1 = property(lambda self: self.data[:, Col.e1], doc="tracking error e1 = x1d − y [m]")
    a1_hat = property(lambda self: self.data[:, Col.a1_hat], doc="estimate â1 [N·s/m]")
    a2_hat = property(lambda self: self.data[:, Col.a2_hat], doc="estimate â2 [m³/(s·Pa)]")
