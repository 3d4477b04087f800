"""Segments of an experiment: short, disjoint windows on which the model's
prediction from a measured state is compared with the measurement."""
from __future__ import annotations

import numpy as np

from has_control.identify.data import Experiment

#: Steps of a segment (28.8 ms at 0.3 ms): long enough that the parameters move
#: the prediction well beyond the sensors' noise and that its fitted initial
#: state is well determined (with 32 steps, the valve lag came out biased by
#: about 1.5 standard errors: the commands of a closed loop depend on the same
#: noise as the measured start), short enough that the open-loop prediction of
#: an integrating cylinder stays close for parameters tens of percent off.
SEGMENT_SAMPLES = 96

#: A segment whose measured pressures come this close to the supply or return
#: pressure (fraction of Ps − Pr) is left out: the plant clips there, and the
#: model's equations do not hold.
PRESSURE_MARGIN = 0.02


def segment_starts(exp: Experiment, length: int = SEGMENT_SAMPLES, skip: int = 1) -> np.ndarray:
    """First samples of disjoint segments of ``length`` steps (one sample apart,
    so no two share a measurement), leaving out the first ``skip`` segments
    and those that touch a pressure bound or a gap of the recording (``exp.gaps``)."""
    a = exp.cfg.plant.actuator(exp.cfg.actuator)
    lo = a.return_pressure + PRESSURE_MARGIN * (a.supply_pressure - a.return_pressure)
    hi = a.supply_pressure - PRESSURE_MARGIN * (a.supply_pressure - a.return_pressure)
    p = exp.x[:, 2:4]
    bad = ((p < lo) | (p > hi)).any(axis=1)
    bad[exp.gaps] = True                     # a sample recorded without a usable state and command
    starts = np.arange(skip * (length + 1), exp.samples - length - 1, length + 1, dtype=np.int64)
    cum = np.concatenate([[0], np.cumsum(bad)])
    clean = cum[starts + length + 1] - cum[starts] == 0
    return starts[clean]
