"""Short-horizon predictions of the actuator, compiled.

Each segment starts from a given state (y [m], ẏ [m/s], P1 [Pa], P2 [Pa])
at its first sample and is stepped ``length`` samples with the recorded valve
commands by the core's own plant step
(:func:`~has_control.core.actuator.valve_plant_step`: RK4, valve travel limit
and lag, pressures clipped into [Pr, Ps]); the prediction is the state at
each of its samples. The spool of a lagging valve depends on the commands
only, so it is carried over the whole recording from a centred spool at
sample 0, as the plant node starts it; between segments only the spool is
of interest (the state is held at the next segment's start). A plant
beyond the reference structure (second-order spool, delay, friction,
substeps) is stepped by :func:`~has_control.core.actuator.spool_plant_step`,
as the episode kernel's general path, with the command of ``delay`` samples
earlier (0 before sample 0) and the spool's velocity carried with it.
"""
from __future__ import annotations

from numba import njit

from has_control.core.actuator import spool_plant_step, valve_plant_step
from has_control.core.jit import KERNEL
from has_control.core.params import DELAY, STRUCTURE, STRUCTURE_REFERENCE


@njit(**KERNEL)
def predict_segments(pp, dt, x0, u, starts, length, out):
    """Fill ``out[s, k]`` (k = 0 … length) with the state at sample
    ``starts[s] + k`` predicted from ``x0[s]`` at ``starts[s]`` under plant
    array ``pp`` (:meth:`~has_control.core.params.Plant.as_array` layout),
    step dt [s]. ``u``: (n,) commands [m]; ``starts`` sorted, segments
    disjoint and inside the recording."""
    nseg = starts.shape[0]
    if nseg == 0:
        return
    s = 0
    xv = 0.0
    wv = 0.0
    general = pp[STRUCTURE] != STRUCTURE_REFERENCE
    d = int(pp[DELAY])
    last = starts[nseg - 1] + length
    x1, x2, x3, x4 = x0[0, 0], x0[0, 1], x0[0, 2], x0[0, 3]
    for i in range(last):
        if i == starts[s]:
            x1, x2, x3, x4 = x0[s, 0], x0[s, 1], x0[s, 2], x0[s, 3]
            out[s, 0, 0] = x1
            out[s, 0, 1] = x2
            out[s, 0, 2] = x3
            out[s, 0, 3] = x4
        inside = starts[s] <= i
        if general:
            y, v, p1, p2, xv, wv = spool_plant_step(x1, x2, x3, x4, xv, wv, u[i - d] if i >= d else 0.0, pp, dt)
        else:
            y, v, p1, p2, xv = valve_plant_step(x1, x2, x3, x4, xv, u[i], pp, dt)
        if inside:
            k = i + 1 - starts[s]
            x1, x2, x3, x4 = y, v, p1, p2
            out[s, k, 0] = y
            out[s, k, 1] = v
            out[s, k, 2] = p1
            out[s, k, 3] = p2
            if k == length:
                s += 1
                if s < nseg:
                    x1, x2, x3, x4 = x0[s, 0], x0[s, 1], x0[s, 2], x0[s, 3]
