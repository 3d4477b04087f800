"""One closed-loop episode (SPEC §5), as a trace or as a parallel batch of costs.

One sample of one candidate is :func:`sample_step` (law, cost, metrics,
adaptation, plant step, divergence test), inlined into both kernels:
``_episode`` runs one candidate and records its trace (``simulate``);
``_block`` runs up to LANES candidates together, structure of arrays, with a
branch-free loop over lanes that LLVM vectorises (``evaluate``, blocks spread
over threads). Both do the same arithmetic per candidate, so they give the
same bits. A plant or sensors beyond the reference structure (a
second-order spool, a delay, friction, substeps, quantised or derived
readings: ``Plant.structure``) run through :func:`general_sample_step` in
kernels of their own, ``_episode_general`` and ``_block_general``, chosen in
Python, so the reference kernels are what they were.
"""
from __future__ import annotations

import math
import os
import threading
from dataclasses import dataclass

import numpy as np
import numba
from numba import njit
from numba.cpython.unsafe.tuple import tuple_setitem
from numba.np.unsafe.ndarray import to_fixed_tuple

from has_control.core.abc_controller import abc_law, adapt
from has_control.core.actuator import diverged, spool_plant_step, valve_plant_step
from has_control.core.cost import Score, cost_increment, metric_finish, metric_update
from has_control.core.jit import INLINE, KERNEL, LEAF
from has_control.core.measures import (
    HF_CORNER, MEASURE_STATE, MEASURES, NO_MEASURES, measure_command, measure_finish, measure_parameters,
    measure_start, measure_state, score_measures,
)
from has_control.core.noise import measurement_noise, noise_on, sensor_readings, sensors_on
from has_control.core.params import (
    A1_INIT, A2_INIT, DELAY, DELAY_RING, DT, N_ACTUATOR, N_CONTROLLER, N_EPISODE, N_PLANT, N_SAMPLES, N_SENSOR,
    STRUCTURE, STRUCTURE_FULL, STRUCTURE_REFERENCE, STRUCTURE_SPOOL, SUBSTEPS, WIN_END, WIN_START,
    X3D_ANALYTIC, X3D_BACKWARD, X3D_MODE, Y_LIMIT, Config, Gains,
)
from has_control.core.reference import check_road_memory, reference, reference_array
from has_control.core.run import TRACE_COLUMNS, TRACE_UNITS, Col, Run
from has_control.core.scenarios import evaluate_scenarios


_NCOL = len(TRACE_COLUMNS)

#: Lanes of one block of the batch kernel: a compile-time constant, so the
#: block's state is one (rows, LANES) array at fixed offsets and LLVM can prove
#: the lanes independent and vectorise the lane loop (AVX2: 4 doubles a vector).
#: A block with fewer candidates pads its last lanes with copies of its last one.
LANES = 8


@njit(**INLINE)
def sample_step(x1, x2, x3, x4, xv, a1_hat, a2_hat, x3d_prev, has_prev, r0, r1, r2, r3, n1, n2, n3, n4, noisy,
                k1, k2, k3, j, mean, m2, peak, count, in_window, ap, pp, cp, ep, dt, y_limit):
    """SPEC §5 steps 3-7 for one candidate at one sample: law, cost, metrics,
    adaptation, plant step and divergence test.

    x1..x4 is the plant's true state and xv its spool [m]; r0..r3 are the
    reference values of the sample; the controller (model ``ap``) reads the
    state plus the noise n1..n4 when ``noisy``, the plant (plant array ``pp``)
    steps the true state, and the cost and metrics take the true
    e1 = x1d − x1. ``count`` is the number of window samples including this
    one, ``in_window`` whether this one is in the window. No branch depends
    on the lane's own values except through selects, so a loop over lanes of
    this function vectorises. Returns the next (x1..x4, xv, â1, â2, x3d, J,
    mean, m2, peak), whether the run diverged, and (u, e1, e2, e3) of this
    sample (e1 the true one; e2, e3 the controller's).
    """
    u, _, e2, e3, rate1, rate2, x3d = abc_law(
        x1 + n1 if noisy else x1, x2 + n2 if noisy else x2, x3 + n3 if noisy else x3, x4 + n4 if noisy else x4,
        a1_hat, a2_hat, x3d_prev, has_prev, r0, r1, r2, r3, k1, k2, k3, ap, cp, dt)
    e1 = r0 - x1                                    # the law's own e1 when there is no noise
    j += cost_increment(e1, u, ep)
    _, mean_w, m2_w, peak_w = metric_update(count - 1.0, mean, m2, peak, e1)
    mean = mean_w if in_window else mean
    m2 = m2_w if in_window else m2
    peak = peak_w if in_window else peak
    b1, b2 = adapt(a1_hat, a2_hat, rate1, rate2, cp, dt)
    y, v, p1, p2, sv = valve_plant_step(x1, x2, x3, x4, xv, u, pp, dt)
    bad = diverged(y, v, p1, p2, y_limit) | (not math.isfinite(u))
    return y, v, p1, p2, sv, b1, b2, x3d, j, mean, m2, peak, bad, u, e1, e2, e3


# rows of a block's lane state (the first _ROWS are the reference kernel's; below)
_X1, _X2, _X3, _X4, _XV, _A1, _A2, _X3D, _J, _MEAN, _M2, _PEAK, _DEAD, _K1, _K2, _K3 = range(16)
_ROWS = 16
#: ... then the general path's: the spool's velocity, the previous position and
#: velocity readings, this sample's command, the delayed command the plant
#: gets, and the ring of the last DELAY_RING commands.
_WV, _YPREV, _VPREV, _U, _UA = range(_ROWS, _ROWS + 5)
_RING = _ROWS + 5
_GENERAL_ROWS = _RING + DELAY_RING


@njit(**INLINE)
def general_sample_step(s, q, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count, in_window, ap, pp, cp, sp, ep,
                        dt, y_limit):
    """:func:`sample_step` of a plant of any structure and sensors of any kind,
    on column q of lane state ``s`` (rows _X1 … _UA), at sample i: the
    controller reads :func:`~has_control.core.noise.sensor_readings`, the
    command goes to row _U and the plant
    (:func:`~has_control.core.actuator.spool_plant_step`) gets it, or with a
    delay d > 0 row _UA (the command of sample i − d, which :func:`_ring_read`
    put there; :func:`_ring_write` stores _U after). Only fixed rows are read
    and written, so a loop over lanes vectorises. Updates ``s``
    in place; returns (diverged, u, e1, e2, e3) as :func:`sample_step` does.
    The same arithmetic per candidate as sample_step's where the options are off."""
    x1, x2, x3, x4 = s[_X1, q], s[_X2, q], s[_X3, q], s[_X4, q]
    a1_hat, a2_hat = s[_A1, q], s[_A2, q]
    has_prev = i > 0
    m1, m2, m3, m4 = sensor_readings(x1, x2, x3, x4, n1, n2, n3, n4, noisy, sp, s[_YPREV, q], s[_VPREV, q],
                                     has_prev, dt)
    s[_YPREV, q] = m1
    s[_VPREV, q] = m2
    u, _, e2, e3, rate1, rate2, x3d = abc_law(
        m1, m2, m3, m4, a1_hat, a2_hat, s[_X3D, q], has_prev, r0, r1, r2, r3, s[_K1, q], s[_K2, q], s[_K3, q],
        ap, cp, dt)
    e1 = r0 - x1
    s[_J, q] += cost_increment(e1, u, ep)
    mean, m2, peak = s[_MEAN, q], s[_M2, q], s[_PEAK, q]
    _, mean_w, m2_w, peak_w = metric_update(count - 1.0, mean, m2, peak, e1)
    s[_MEAN, q] = mean_w if in_window else mean
    s[_M2, q] = m2_w if in_window else m2
    s[_PEAK, q] = peak_w if in_window else peak
    s[_A1, q], s[_A2, q] = adapt(a1_hat, a2_hat, rate1, rate2, cp, dt)
    s[_X3D, q] = x3d
    s[_U, q] = u
    d = pp[DELAY]
    applied = u if d == 0.0 else (s[_UA, q] if d >= 1.0 else s[_UA, q] + (1.0 - d) * u)
    y, v, p1, p2, sv, wv = spool_plant_step(x1, x2, x3, x4, s[_XV, q], s[_WV, q], applied, pp, dt)
    s[_X1, q], s[_X2, q], s[_X3, q], s[_X4, q], s[_XV, q], s[_WV, q] = y, v, p1, p2, sv, wv
    bad = diverged(y, v, p1, p2, y_limit) | (not math.isfinite(u))
    return bad, u, e1, e2, e3


@njit(**LEAF)
def _ring_read(s, i, pp):
    """Row _UA = the ring's command of sample i − d (d = pp[DELAY]; 0 before sample 0), every lane; with a
    fraction f of d, (1 − f)·u(i − ⌊d⌋) + f·u(i − ⌊d⌋ − 1), the first term left to
    :func:`general_sample_step` when ⌊d⌋ = 0 (this sample's command is not in the ring yet)."""
    d = pp[DELAY]
    n = int(d)
    f = d - n
    slot = _RING + (i + DELAY_RING - n) % DELAY_RING
    if f == 0.0:
        for q in range(s.shape[1]):
            s[_UA, q] = s[slot, q]
        return
    before = _RING + (i + DELAY_RING - n - 1) % DELAY_RING
    for q in range(s.shape[1]):
        s[_UA, q] = f * s[before, q] if n == 0 else (1.0 - f) * s[slot, q] + f * s[before, q]


@njit(**LEAF)
def _ring_write(s, i):
    """The ring's slot i mod DELAY_RING = row _U (the command of sample i), every lane."""
    slot = _RING + i % DELAY_RING
    for q in range(s.shape[1]):
        s[slot, q] = s[_U, q]


@njit(**LEAF)
def _structure(pp, sp):
    """The structure the kernels run (STRUCTURE_*): the plant's, or with
    quantised or derived sensor readings at least STRUCTURE_SPOOL (the general path)."""
    st = int(pp[STRUCTURE])
    return STRUCTURE_SPOOL if (st == STRUCTURE_REFERENCE) & sensors_on(sp) else st


@njit(**LEAF)
def _as_structure(pp, st):
    """``pp`` (a tuple) with its structure the constant ``st`` (and one substep
    below STRUCTURE_FULL): a lane loop given it compiles the other structures away."""
    pp = tuple_setitem(pp, STRUCTURE, float(st))
    return pp if st == STRUCTURE_FULL else tuple_setitem(pp, SUBSTEPS, 1.0)


@njit(**LEAF)
def _constants(ap, pp, cp, sp, ep):
    """The parameter arrays as tuples (in a loop, their entries are values
    rather than loads from memory LLVM cannot prove unaliased), and the grid:
    (ap, pp, cp, sp, whether there is noise, ep, dt, samples, first and last
    window sample, y_limit)."""
    ept = to_fixed_tuple(ep, N_EPISODE)
    spt = to_fixed_tuple(sp, N_SENSOR)
    noisy = noise_on(spt)
    return (to_fixed_tuple(ap, N_ACTUATOR), to_fixed_tuple(pp, N_PLANT), to_fixed_tuple(cp, N_CONTROLLER), spt,
            noisy, ept, ept[DT], int(ept[N_SAMPLES]), int(ept[WIN_START]), int(ept[WIN_END]), ept[Y_LIMIT])


@njit(**LEAF)
def put_trace_row(row, t, x1d, y, ydot, p1, p2, u, e1, e2, e3, a1_hat, a2_hat):
    """One sample's row of a trace, in TRACE_COLUMNS order (the sample's state
    and the estimates it was controlled with)."""
    values = (t, x1d, y, ydot, p1, p2, u, e1, e2, e3, a1_hat, a2_hat)
    for k in range(len(values)):
        row[k] = values[k]


#: Samples whose reference the kernels compute ahead, in a loop of their own:
#: the sample loop then holds no reference code (a road's sum in it made the
#: sine's batch 3.5 % slower).
_AHEAD = 256


@njit(**INLINE)
def _reference_ahead(rp, start, n, dt, ref):
    """Rows 0.. of ``ref`` = :func:`reference` at samples start, start + 1, …
    (at most ``len(ref)``, none past n); returns how many."""
    ahead = min(ref.shape[0], n - start)
    for a in range(ahead):
        ref[a, 0], ref[a, 1], ref[a, 2], ref[a, 3] = reference(rp, (start + a) * dt)
    return ahead


@njit(**KERNEL)
def _episode_general(k1, k2, k3, ap, pp, cp, rp, sp, seed, ep, x0, trace):
    """:func:`_episode` through :func:`general_sample_step` (one lane), for a
    plant or sensors beyond the reference structure (a kernel of its own, so
    the reference's compiles no more than before)."""
    ap, pp, cp, sp, noisy, ep, dt, n, lo, hi, y_limit = _constants(ap, pp, cp, sp, ep)
    record = trace.shape[0] > 0
    s = np.zeros((_GENERAL_ROWS, 1))
    s[_X1, 0], s[_X2, 0], s[_X3, 0], s[_X4, 0] = x0[0], x0[1], x0[2], x0[3]
    s[_A1, 0] = cp[A1_INIT]
    s[_A2, 0] = cp[A2_INIT]
    s[_K1, 0], s[_K2, 0], s[_K3, 0] = k1, k2, k3
    count = 0.0
    ref = np.empty((_AHEAD, 4))
    for start in range(0, n, _AHEAD):
        ahead = _reference_ahead(rp, start, n, dt, ref)
        for a in range(ahead):
            i = start + a
            r0, r1, r2, r3 = ref[a, 0], ref[a, 1], ref[a, 2], ref[a, 3]
            n1, n2, n3, n4 = measurement_noise(sp, seed, i) if noisy else (0.0, 0.0, 0.0, 0.0)
            in_window = lo <= i <= hi
            if in_window:
                count += 1.0
            x1, x2, x3, x4, a1_hat, a2_hat = s[_X1, 0], s[_X2, 0], s[_X3, 0], s[_X4, 0], s[_A1, 0], s[_A2, 0]
            _ring_read(s, i, pp)
            bad, u, e1, e2, e3 = general_sample_step(s, 0, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count,
                                                     in_window, ap, pp, cp, sp, ep, dt, y_limit)
            _ring_write(s, i)
            if record:
                put_trace_row(trace[i], i * dt, r0, x1, x2, x3, x4, u, e1, e2, e3, a1_hat, a2_hat)
            if bad:
                return math.inf, math.inf, math.inf, math.inf, i + 1, True
    e_max, e_mu, e_sigma = metric_finish(count, s[_MEAN, 0], s[_M2, 0], s[_PEAK, 0])
    return s[_J, 0], e_max, e_mu, e_sigma, n, False


@njit(**KERNEL)
def _episode(k1, k2, k3, ap, pp, cp, rp, sp, seed, ep, x0, trace):
    """Run one episode; fill ``trace`` rows if it has any (the true state, the
    command, the true e1 and the controller's e2, e3 and estimates). Returns
    (J, e_max, e_μ, e_σ, samples, diverged)."""
    ap, pp, cp, sp, noisy, ep, dt, n, lo, hi, y_limit = _constants(ap, pp, cp, sp, ep)
    record = trace.shape[0] > 0
    x1 = x0[0]
    x2 = x0[1]
    x3 = x0[2]
    x4 = x0[3]
    xv = 0.0
    a1_hat = cp[A1_INIT]
    a2_hat = cp[A2_INIT]
    x3d = 0.0
    j = 0.0
    count = mean = m2 = peak = 0.0
    ref = np.empty((_AHEAD, 4))
    for start in range(0, n, _AHEAD):
        ahead = _reference_ahead(rp, start, n, dt, ref)
        for a in range(ahead):
            i = start + a
            t = i * dt
            r0, r1, r2, r3 = ref[a, 0], ref[a, 1], ref[a, 2], ref[a, 3]
            n1, n2, n3, n4 = measurement_noise(sp, seed, i) if noisy else (0.0, 0.0, 0.0, 0.0)
            in_window = lo <= i <= hi
            if in_window:
                count += 1.0
            y, v, p1, p2, sv, b1, b2, x3d, j, mean, m2, peak, bad, u, e1, e2, e3 = sample_step(
                x1, x2, x3, x4, xv, a1_hat, a2_hat, x3d, i > 0, r0, r1, r2, r3, n1, n2, n3, n4, noisy, k1, k2, k3,
                j, mean, m2, peak, count, in_window, ap, pp, cp, ep, dt, y_limit)
            if record:
                put_trace_row(trace[i], t, r0, x1, x2, x3, x4, u, e1, e2, e3, a1_hat, a2_hat)
            if bad:
                return math.inf, math.inf, math.inf, math.inf, i + 1, True
            x1, x2, x3, x4, xv, a1_hat, a2_hat = y, v, p1, p2, sv, b1, b2
    e_max, e_mu, e_sigma = metric_finish(count, mean, m2, peak)
    return j, e_max, e_mu, e_sigma, n, False


@njit(**INLINE)
def _lanes(s, has_prev, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count, in_window, ap, pp, cp, ep, dt, y_limit,
           mark):
    """One sample of every lane of a block: the loop LLVM vectorises. A lane
    that diverges at this sample gets ``mark`` in its _DEAD row."""
    for q in range(LANES):
        (s[_X1, q], s[_X2, q], s[_X3, q], s[_X4, q], s[_XV, q], s[_A1, q], s[_A2, q], s[_X3D, q], s[_J, q],
         s[_MEAN, q], s[_M2, q], s[_PEAK, q], bad, _, _, _, _) = sample_step(
            s[_X1, q], s[_X2, q], s[_X3, q], s[_X4, q], s[_XV, q], s[_A1, q], s[_A2, q], s[_X3D, q], has_prev,
            r0, r1, r2, r3, n1, n2, n3, n4, noisy, s[_K1, q], s[_K2, q], s[_K3, q],
            s[_J, q], s[_MEAN, q], s[_M2, q], s[_PEAK, q], count, in_window, ap, pp, cp, ep, dt, y_limit)
        dead = s[_DEAD, q]
        s[_DEAD, q] = dead if dead > 0.0 else (mark if bad else 0.0)


@njit(**INLINE)
def _lanes_general(s, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count, in_window, ap, pp, cp, sp, ep, dt, y_limit,
                   mark, measure, m, mp):
    """:func:`_lanes` through :func:`general_sample_step`, the delay's ring
    read before the lane loop and written after it; with ``measure`` the
    lanes' :mod:`~has_control.core.measures` in ``m`` (parameters ``mp``),
    in loops of their own around it."""
    _ring_read(s, i, pp)
    if measure:
        for q in range(LANES):
            measure_state(m, q, r0 - s[_X1, q], s[_X3, q], s[_X4, q])
    for q in range(LANES):
        bad, _, _, _, _ = general_sample_step(s, q, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count, in_window,
                                              ap, pp, cp, sp, ep, dt, y_limit)
        dead = s[_DEAD, q]
        s[_DEAD, q] = dead if dead > 0.0 else (mark if bad else 0.0)
    if measure:
        for q in range(LANES):
            measure_command(m, q, s[_U, q], in_window, mp, ep)
    _ring_write(s, i)


@njit(**INLINE)
def _block_start(s, gains, first, last, cp, x0):
    """Lane q of ``s`` = candidate first + q at x0 (lanes past ``last`` copy its last candidate)."""
    for q in range(LANES):
        p = min(first + q, last - 1)
        s[_X1, q] = x0[0]
        s[_X2, q] = x0[1]
        s[_X3, q] = x0[2]
        s[_X4, q] = x0[3]
        s[_A1, q] = cp[A1_INIT]
        s[_A2, q] = cp[A2_INIT]
        s[_K1, q] = gains[p, 0]
        s[_K2, q] = gains[p, 1]
        s[_K3, q] = gains[p, 2]


@njit(**LEAF)
def _alive(s):
    """Lanes of ``s`` that have not diverged."""
    alive = 0
    for q in range(LANES):
        alive += s[_DEAD, q] == 0.0
    return alive


@njit(**INLINE)
def _block_finish(s, first, last, count, n, out):
    """Rows first..last-1 of ``out``: (J, e_max, e_μ, e_σ, samples, diverged) of each lane."""
    for q in range(min(last - first, LANES)):           # the caller never passes more
        p = first + q
        if s[_DEAD, q] > 0.0:
            out[p, 0] = out[p, 1] = out[p, 2] = out[p, 3] = math.inf
            out[p, 4] = s[_DEAD, q]
            out[p, 5] = 1.0
        else:
            e_max, e_mu, e_sigma = metric_finish(count, s[_MEAN, q], s[_M2, q], s[_PEAK, q])
            out[p, 0] = s[_J, q]
            out[p, 1] = e_max
            out[p, 2] = e_mu
            out[p, 3] = e_sigma
            out[p, 4] = n
            out[p, 5] = 0.0


@njit(**KERNEL)
def _block(gains, first, last, ap, pp, cp, rp, sp, seed, ep, x0, out):
    """Episodes of candidates first..last-1 (at most LANES) advanced sample by
    sample together, structure of arrays: lane q of row r is ``s[r, q]``;
    a plant and sensors of the reference structure (others:
    :func:`_block_general`).

    The lane loop calls :func:`sample_step`, as :func:`_episode` does, so a
    candidate's score does not depend on which block or lane it ran in. A
    diverged lane goes on computing (its results are discarded); the block
    stops when every lane has diverged. The ẋ3d mode is made a constant in
    each of two copies of the lane loop, so neither computes the other mode's
    division (4 % faster than one loop computing both).
    """
    ap, pp, cp, sp, noisy, ep, dt, n, lo, hi, y_limit = _constants(ap, pp, cp, sp, ep)
    backward = int(cp[X3D_MODE]) == X3D_BACKWARD
    cp_analytic = tuple_setitem(cp, X3D_MODE, float(X3D_ANALYTIC))
    cp_backward = tuple_setitem(cp, X3D_MODE, float(X3D_BACKWARD))
    s = np.zeros((_ROWS, LANES))
    _block_start(s, gains, first, last, cp, x0)
    count = 0.0
    ref = np.empty((_AHEAD, 4))
    alive = LANES
    for start in range(0, n, _AHEAD):
        if alive == 0:
            break
        ahead = _reference_ahead(rp, start, n, dt, ref)
        for j in range(ahead):
            i = start + j
            n1, n2, n3, n4 = measurement_noise(sp, seed, i) if noisy else (0.0, 0.0, 0.0, 0.0)
            in_window = lo <= i <= hi
            if in_window:
                count += 1.0
            if backward:
                _lanes(s, i > 0, ref[j, 0], ref[j, 1], ref[j, 2], ref[j, 3], n1, n2, n3, n4, noisy, count,
                       in_window, ap, pp, cp_backward, ep, dt, y_limit, i + 1.0)
            else:
                _lanes(s, i > 0, ref[j, 0], ref[j, 1], ref[j, 2], ref[j, 3], n1, n2, n3, n4, noisy, count,
                       in_window, ap, pp, cp_analytic, ep, dt, y_limit, i + 1.0)
            alive = _alive(s)
            if alive == 0:
                break
    _block_finish(s, first, last, count, n, out)


@njit(**KERNEL)
def _block_general(gains, first, last, ap, pp, cp, rp, sp, seed, ep, x0, mp, out):
    """:func:`_block` for a plant or sensors beyond the reference structure,
    through :func:`general_sample_step`: the structure (spool or full) is
    made a constant in each copy of the lane loop (and the ẋ3d mode in the
    spool structure's two), so a copy compiles the options it has not away:
    a second-order spool with a delay runs as fast as the reference plant.

    ``mp`` (:func:`~has_control.core.measures.measure_parameters`, or
    NO_MEASURES): with mp[0] = 1 columns 6.. of ``out`` get the MEASURES of
    each lane's run (``out`` then has 6 + len(MEASURES) columns)."""
    ap, pp, cp, sp, noisy, ep, dt, n, lo, hi, y_limit = _constants(ap, pp, cp, sp, ep)
    measure = mp[0] != 0.0
    m = np.zeros((MEASURE_STATE, LANES))
    for q in range(LANES):
        measure_start(m, q)
    backward = int(cp[X3D_MODE]) == X3D_BACKWARD
    cp_analytic = tuple_setitem(cp, X3D_MODE, float(X3D_ANALYTIC))
    cp_backward = tuple_setitem(cp, X3D_MODE, float(X3D_BACKWARD))
    full = _structure(pp, sp) == STRUCTURE_FULL
    pp_spool = _as_structure(pp, STRUCTURE_SPOOL)
    pp_full = _as_structure(pp, STRUCTURE_FULL)
    s = np.zeros((_GENERAL_ROWS, LANES))
    _block_start(s, gains, first, last, cp, x0)
    count = 0.0
    ref = np.empty((_AHEAD, 4))
    alive = LANES
    for start in range(0, n, _AHEAD):
        if alive == 0:
            break
        ahead = _reference_ahead(rp, start, n, dt, ref)
        for j in range(ahead):
            i = start + j
            n1, n2, n3, n4 = measurement_noise(sp, seed, i) if noisy else (0.0, 0.0, 0.0, 0.0)
            in_window = lo <= i <= hi
            if in_window:
                count += 1.0
            r0, r1, r2, r3 = ref[j, 0], ref[j, 1], ref[j, 2], ref[j, 3]
            if full:
                _lanes_general(s, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count, in_window, ap, pp_full,
                               cp, sp, ep, dt, y_limit, i + 1.0, measure, m, mp)
            elif backward:
                _lanes_general(s, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count, in_window, ap, pp_spool,
                               cp_backward, sp, ep, dt, y_limit, i + 1.0, measure, m, mp)
            else:
                _lanes_general(s, i, r0, r1, r2, r3, n1, n2, n3, n4, noisy, count, in_window, ap, pp_spool,
                               cp_analytic, sp, ep, dt, y_limit, i + 1.0, measure, m, mp)
            alive = _alive(s)
            if alive == 0:
                break
    _block_finish(s, first, last, count, n, out)
    if measure:
        for q in range(min(last - first, LANES)):
            p = first + q
            if s[_DEAD, q] > 0.0:
                for c in range(6, out.shape[1]):
                    out[p, c] = math.inf
            else:
                measure_finish(m, q, count, n, out[p], 6)


def threads() -> int:
    """Threads :func:`evaluate` runs on: NUMBA_NUM_THREADS (default: every core)."""
    return max(1, int(numba.config.NUMBA_NUM_THREADS))


def _block_edges(count: int, workers: int) -> np.ndarray:
    """Split ``count`` candidates into blocks of at most LANES, a multiple of
    the thread count so every core gets the same share."""
    blocks = workers * max(1, math.ceil(count / (workers * LANES)))
    blocks = max(1, min(blocks, count))
    return np.linspace(0, count, blocks + 1).round().astype(np.int64)


_POOL = (None, 0, 0)          # (executor, workers, pid that made it)
_POOL_LOCK = threading.Lock()


def _pool(workers: int):
    """One thread pool for every call of :func:`evaluate` (starting threads
    anew cost about 2 ms a call, 4-5 % of scoring 80 candidates). A forked
    child, which has none of the parent's threads, makes its own."""
    global _POOL
    with _POOL_LOCK:
        pool, size, pid = _POOL
        if pool is None or size != workers or pid != os.getpid():
            from concurrent.futures import ThreadPoolExecutor
            pool = ThreadPoolExecutor(workers, thread_name_prefix="has_control-evaluate")
            _POOL = (pool, workers, os.getpid())
        return pool


def _run_blocks(gains, arrays: "list[EpisodeArrays]", outs, workers: int | None = None, mps=None) -> None:
    """Every block of ``gains`` under every ``arrays[s]`` (into ``outs[s]``) on
    ``workers`` threads (default :func:`threads`). ``_block`` releases the GIL,
    so Python threads run blocks in parallel; each block writes its own rows of
    its own ``out``, so the result does not depend on the schedule. With
    ``mps`` (measure parameters, one per array) every block runs
    ``_block_general``, which measures (``outs[s]`` then has the measures' columns)."""
    if gains.shape[0] == 0 or not arrays:
        return
    workers = workers or threads()
    edges = _block_edges(gains.shape[0], max(1, workers // len(arrays)) if len(arrays) < workers else 1)
    tasks = [(s, b) for s in range(len(arrays)) for b in range(len(edges) - 1)]

    def run(task):
        s, b = task
        if mps is None and arrays[s].structure() == STRUCTURE_REFERENCE:
            _block(gains, edges[b], edges[b + 1], *arrays[s].kernel_args(), outs[s])
        else:
            _block_general(gains, edges[b], edges[b + 1], *arrays[s].kernel_args(),
                           NO_MEASURES if mps is None else mps[s], outs[s])
    if workers == 1 or len(tasks) == 1:
        for task in tasks:
            run(task)
        return
    list(_pool(workers).map(run, tasks))


@dataclass(frozen=True)
class EpisodeArrays:
    """The flat arrays the kernel reads, built once from a :class:`Config`:
    the controller's model (``actuator``), the plant's (``plant``), the
    adaptation, the reference (a road tabulated on the episode's grid), the
    sensor noise's standard deviations and seed, the grid, and the plant's
    initial state (its own static equilibrium, SPEC §4)."""

    actuator: np.ndarray
    plant: np.ndarray
    adaptation: np.ndarray
    reference: np.ndarray
    sensor: np.ndarray
    seed: int
    episode: np.ndarray
    x0: np.ndarray

    @classmethod
    def from_config(cls, cfg: Config) -> "EpisodeArrays":
        return cls(cfg.actuator.as_array(), cfg.plant.as_array(cfg.actuator), cfg.adaptation.as_array(),
                   reference_array(cfg.reference, cfg.episode), cfg.noise.as_array(cfg.episode.step),
                   int(cfg.noise.seed), cfg.episode.as_array(), cfg.plant.actuator(cfg.actuator).initial_state())

    def structure(self) -> int:
        """The structure the kernels run (STRUCTURE_*; :func:`_structure`)."""
        return int(_structure(self.plant, self.sensor))

    def kernel_args(self) -> tuple:
        """(ap, pp, cp, rp, sp, seed, ep, x0): the arguments the kernels take after the gains."""
        return (self.actuator, self.plant, self.adaptation, self.reference, self.sensor, self.seed, self.episode,
                self.x0)


@dataclass(frozen=True)
class Trace(Run):
    """One simulated episode: its :class:`~has_control.core.run.Run` (every column), its score and its gains."""

    score: Score
    gains: Gains


def simulate(cfg: Config | None = None, gains: Gains | tuple | None = None,
             x0: np.ndarray | None = None) -> Trace:
    """Run one episode and return its :class:`Trace`.

    ``gains`` defaults to ``cfg.gains``; ``x0`` (y, ẏ, P1, P2) to SPEC §4's
    initial state. A diverged run's trace stops at the sample that diverged.
    """
    cfg = cfg or Config()
    g = _as_gains(gains if gains is not None else cfg.gains)
    arr = EpisodeArrays.from_config(cfg)
    start = arr.x0 if x0 is None else np.asarray(x0, dtype=np.float64)
    trace = np.zeros((cfg.episode.samples, _NCOL))
    kernel = _episode if arr.structure() == STRUCTURE_REFERENCE else _episode_general
    j, a, b, c, n, bad = kernel(g.k1, g.k2, g.k3, *arr.kernel_args()[:-1], start, trace)
    return Trace(trace[:n], Score(j, a, b, c, int(n), bool(bad)), g)


def _gains_array(gains) -> np.ndarray:
    k = np.ascontiguousarray(np.atleast_2d(np.asarray(gains, dtype=np.float64)))
    if k.ndim != 2 or k.shape[1] != 3:
        raise ValueError(f"gains: expected shape (P, 3), got {np.shape(gains)}")
    return k


def evaluate(gains, cfg: Config | None = None, metrics: bool = False, scenarios=None, aggregate="mean"):
    """Score many gain sets in parallel.

    gains: (P, 3) array of (k1, k2, k3). Returns the (P,) costs J, or with
    ``metrics`` a (P, 4) array of (J, e_max, e_μ, e_σ). Diverged runs give +inf.
    Deterministic: each row depends on its gains only.

    With ``scenarios`` (a sequence of :class:`~has_control.core.scenarios.Scenario`)
    returns their :class:`~has_control.core.scenarios.ScenarioScores` instead: the
    per-scenario metrics and the ``aggregate`` (mean, max, cvar:α) of J.
    """
    if scenarios is not None:
        return evaluate_scenarios(gains, cfg or Config(), scenarios, aggregate, evaluate_configs)
    out = evaluate_configs(gains, [cfg or Config()])[:, 0]
    return out.copy() if metrics else out[:, 0].copy()


def evaluate_configs(gains, cfgs, workers: int | None = None) -> np.ndarray:
    """Every gain set under every configuration (a scenario set), on
    ``workers`` threads (default :func:`threads`).

    gains: (P, 3); cfgs: S Configs. Returns the (P, S, 4) array of
    (J, e_max, e_μ, e_σ); a diverged run gives +inf. Row (p, s) depends on
    gains[p] and cfgs[s] only, so any split of the work (threads, blocks,
    Dask tasks) gives the same bits.
    """
    k = _gains_array(gains)
    check_road_memory([(c.reference, c.episode) for c in cfgs])
    arrays = [EpisodeArrays.from_config(c) for c in cfgs]
    outs = [np.empty((k.shape[0], 6)) for _ in arrays]
    _run_blocks(k, arrays, outs, workers)
    res = np.empty((k.shape[0], len(arrays), 4))
    for s, out in enumerate(outs):
        res[:, s] = out[:, :4]
    return res


def evaluate_measured(gains, cfgs, corner: float = HF_CORNER, workers: int | None = None) -> np.ndarray:
    """:func:`evaluate_configs` with each run's
    :data:`~has_control.core.measures.MEASURES` after its (J, e_max, e_μ,
    e_σ): the (P, S, 4 + len(MEASURES)) array; ``corner`` [Hz]: the high-pass
    corner of ``hf_rms``. Every run goes through the general kernel, whose
    J is the reference kernel's to the bit where the options are off."""
    k = _gains_array(gains)
    check_road_memory([(c.reference, c.episode) for c in cfgs])
    arrays = [EpisodeArrays.from_config(c) for c in cfgs]
    outs = [np.empty((k.shape[0], 6 + len(MEASURES))) for _ in arrays]
    _run_blocks(k, arrays, outs, workers,
                [measure_parameters(c.plant.valve_limit, corner, c.episode.step) for c in cfgs])
    res = np.empty((k.shape[0], len(arrays), 4 + len(MEASURES)))
    for s, out in enumerate(outs):
        res[:, s, :4] = out[:, :4]
        res[:, s, 4:] = out[:, 6:]
    return res


def series_measures(trace: "Trace", cfg: Config, corner: float = HF_CORNER) -> dict:
    """The MEASURES of a simulated run, by name (as :func:`evaluate_measured` measures it)."""
    out = np.empty(len(MEASURES))
    score_measures(np.ascontiguousarray(trace["u"]), np.ascontiguousarray(trace["e1"]),
                   np.ascontiguousarray(trace["P1"]), np.ascontiguousarray(trace["P2"]),
                   measure_parameters(cfg.plant.valve_limit, corner, cfg.episode.step), cfg.episode.as_array(), out)
    return dict(zip(MEASURES, (float(v) for v in out)))


def _as_gains(g) -> Gains:
    if isinstance(g, Gains):
        return g
    k1, k2, k3 = (float(v) for v in g)
    return Gains(k1, k2, k3)


__all__ = ["Col", "TRACE_COLUMNS", "TRACE_UNITS", "EpisodeArrays", "Trace", "simulate", "evaluate", "evaluate_configs",
           "evaluate_measured", "series_measures"]
