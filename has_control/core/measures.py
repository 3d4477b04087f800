"""What a machine's requirements are stated in, measured over one run
(``has_control.tuning.requirements`` turns them into an objective).

Per sample, beside the paper's J (:mod:`has_control.core.cost`):

* ``J_window``: J's increments over the metric window only [m·s + m²·s]
  (the start-up transient not charged to the gains);
* ``at_stop``: the share of the run's samples whose command is at the
  spool's travel, |u| ≥ 0.98·u_max (the deployment watchdog's level; 0 with
  no travel limit) [-];
* ``p_min``, ``p_max``: the lowest and highest chamber pressure of the run [Pa];
* ``hf_rms``: the RMS over the metric window of the command minus its
  first-order low-pass at a corner frequency [m] (a limit cycle of the valve
  loop is tens of hertz of command);
* ``u_peak``: the largest |u| of the run [m].

The same :func:`measure_state` and :func:`measure_command` serve the batch kernel (each lane of
``_block_general``) and :func:`score_measures` (a recorded or simulated
series), so both give the same bits.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from has_control.core.cost import cost_increment
from has_control.core.jit import KERNEL, LEAF
from has_control.core.params import WIN_END, WIN_START

#: The measures, in the order of the arrays below.
MEASURES = ("J_window", "at_stop", "p_min", "p_max", "hf_rms", "u_peak")
#: Slots of a run's measure state: the window's cost, samples at the stop, the
#: pressures' range, the low-pass, the window's high-pass energy, the peak
#: command, and the sample's e1 between :func:`measure_state` and :func:`measure_command`.
M_JW, M_STOP, M_PMIN, M_PMAX, M_LOW, M_HF, M_UPEAK, M_E1 = range(8)
MEASURE_STATE = 8
#: The travel share at which the spool counts as at its stop.
AT_STOP_LEVEL = 0.98
#: The default corner of ``hf_rms`` [Hz] (the watchdog's).
HF_CORNER = 20.0


def measure_parameters(valve_limit: float, corner: float, step: float) -> np.ndarray:
    """(1: measure, the stop level [m] (inf without a travel limit), the
    low-pass's α at ``corner`` [Hz] and sample step ``step`` [s])."""
    stop = AT_STOP_LEVEL * valve_limit if valve_limit > 0.0 else math.inf
    return np.array([1.0, stop, 1.0 - math.exp(-2.0 * math.pi * corner * step)])


#: The parameters of a run that measures nothing (the kernels skip the measures).
NO_MEASURES = np.zeros(3)


@njit(**LEAF)
def measure_start(m, q):
    """Column q of measure state ``m`` before the first sample."""
    m[M_JW, q] = m[M_STOP, q] = m[M_LOW, q] = m[M_HF, q] = m[M_UPEAK, q] = 0.0
    m[M_PMIN, q] = math.inf
    m[M_PMAX, q] = -math.inf


@njit(**LEAF)
def measure_state(m, q, e1, p1, p2):
    """Column q of ``m`` given the state of a sample: true error e1 [m]
    (kept for :func:`measure_command`) and the pressures p1, p2 [Pa]."""
    m[M_E1, q] = e1
    m[M_PMIN, q] = min(m[M_PMIN, q], min(p1, p2))
    m[M_PMAX, q] = max(m[M_PMAX, q], max(p1, p2))


@njit(**LEAF)
def measure_command(m, q, u, in_window, mp, ep):
    """Column q of ``m`` given the sample's command u [m] (after
    :func:`measure_state`); ``mp``: :func:`measure_parameters`."""
    if in_window:
        m[M_JW, q] += cost_increment(m[M_E1, q], u, ep)
    au = abs(u)
    if au >= mp[1]:
        m[M_STOP, q] += 1.0
    low = m[M_LOW, q] + mp[2] * (u - m[M_LOW, q])
    m[M_LOW, q] = low
    if in_window:
        h = u - low
        m[M_HF, q] += h * h
    m[M_UPEAK, q] = max(m[M_UPEAK, q], au)


@njit(**LEAF)
def measure_finish(m, q, count, n, out, c):
    """Columns c.. of ``out`` (a row): the MEASURES of column q of ``m`` after
    n samples, ``count`` of them in the window."""
    out[c] = m[M_JW, q]
    out[c + 1] = m[M_STOP, q] / n if n > 0 else math.nan
    out[c + 2] = m[M_PMIN, q]
    out[c + 3] = m[M_PMAX, q]
    out[c + 4] = math.sqrt(m[M_HF, q] / count) if count > 0.0 else math.nan
    out[c + 5] = m[M_UPEAK, q]


@njit(**KERNEL)
def score_measures(u, e1, p1, p2, mp, ep, out):
    """``out`` = the MEASURES of a recorded or simulated series (u, e1 [m],
    p1, p2 [Pa], on the grid of ``ep``): as the batch kernel measures a run."""
    m = np.zeros((MEASURE_STATE, 1))
    measure_start(m, 0)
    lo, hi = int(ep[WIN_START]), int(ep[WIN_END])
    count = 0.0
    for i in range(u.shape[0]):
        in_window = lo <= i <= hi
        count += 1.0 if in_window else 0.0
        measure_state(m, 0, e1[i], p1[i], p2[i])
        measure_command(m, 0, u[i], in_window, mp, ep)
    measure_finish(m, 0, count, u.shape[0], out, 0)
