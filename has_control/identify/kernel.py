"""Short-horizon predictions of the actuator from measured states, compiled.

Each segment starts from the measured state (y [m], ẏ [m/s], P1 [Pa], P2 [Pa])
at its first sample and is stepped ``length`` samples with the recorded valve
commands by the core's own plant step
(:func:`~has_control.core.actuator.valve_plant_step`: RK4, valve travel limit
and lag, pressures clipped into [Pr, Ps]); the prediction is the state at its
last sample. The spool of a lagging valve depends on the commands only, so it
is carried over the whole recording from a centred spool at sample 0, as the
plant node starts it; between segments the state is reset to the measurement
every sample (only the spool matters there).
"""
from __future__ import annotations

from numba import njit

from has_control.core.actuator import valve_plant_step
from has_control.core.jit import KERNEL


@njit(**KERNEL)
def predict_segments(pp, dt, x, u, starts, length, out):
    """Fill ``out[s]`` with the state predicted at sample ``starts[s] + length``
    from the measured ``x[starts[s]]`` under plant array ``pp`` (the
    :meth:`~has_control.core.params.Plant.as_array` layout), step dt [s].
    ``x``: (n, 4) measured states; ``u``: (n,) commands [m]; ``starts`` sorted,
    segments disjoint and inside the recording."""
    n = x.shape[0]
    nseg = starts.shape[0]
    s = 0
    xv = 0.0
    x1, x2, x3, x4 = x[0, 0], x[0, 1], x[0, 2], x[0, 3]
    last = starts[nseg - 1] + length if nseg else 0
    for i in range(min(n - 1, last)):
        inside = s < nseg and starts[s] < i
        if not inside:
            x1, x2, x3, x4 = x[i, 0], x[i, 1], x[i, 2], x[i, 3]
        x1, x2, x3, x4, xv = valve_plant_step(x1, x2, x3, x4, xv, u[i], pp, dt)
        if s < nseg and i + 1 == starts[s] + length:
            out[s, 0] = x1
            out[s, 1] = x2
            out[s, 2] = x3
            out[s, 3] = x4
            s += 1
