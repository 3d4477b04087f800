"""One sample of the plant and of the controller, on serialized messages.

The nodes' fast path: each callback is one compiled call that decodes the
message in hand, runs the one implementation of the physics or the control
law (:func:`~has_control.core.actuator.plant_step`,
:func:`~has_control.core.abc_controller.abc_law`, ``adapt``,
:func:`~has_control.core.reference.reference`, exactly as the episode kernel
calls them) and encodes the answer into preallocated buffers laid out by
:mod:`has_control.wire.topics`. Nothing is allocated per sample.

A decoder returns the sample index of the message, or
:data:`~has_control.wire.codec.MALFORMED` (another layout, a stamp off the grid) or
:data:`~has_control.wire.codec.NOT_FINITE` (a NaN or infinite value); either is
refused before it reaches the state.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from has_control.core.abc_controller import abc_law, adapt
from has_control.core.actuator import diverged, joint_state, spool_plant_step, valve_plant_step
from has_control.core.jit import KERNEL
from has_control.core.noise import measurement_noise, noise_on, sensor_readings, sensors_on
from has_control.core.reference import reference
from has_control.wire.topics import (CLOCK_LAYOUT, COMMAND_LAYOUT, CONTROLLER_STATE_LAYOUT, REFERENCE_LAYOUT,
                                     STATE_LAYOUT)
from has_control.wire.codec import MALFORMED, NOT_FINITE, get_f64, matches, put_f64, put_stamp, sample_of_stamp
from has_control.core.episode import EpisodeArrays, TRACE_COLUMNS, put_trace_row
from has_control.core.params import DELAY, DELAY_RING, STRUCTURE, STRUCTURE_REFERENCE, Config

# Layouts as module constants: numba freezes them into the compiled code.
_STATE_T, _STATE_FIXED, _STATE_V = STATE_LAYOUT.template, STATE_LAYOUT.fixed, STATE_LAYOUT.values
_COMMAND_T, _COMMAND_FIXED, _COMMAND_V = COMMAND_LAYOUT.template, COMMAND_LAYOUT.fixed, COMMAND_LAYOUT.values
_INTERNALS_V = CONTROLLER_STATE_LAYOUT.values
_REFERENCE_V = REFERENCE_LAYOUT.values
assert CLOCK_LAYOUT.stamped and len(CLOCK_LAYOUT.values) == 0

#: Slots of the controller's memory array (float64); Y_PREV, V_PREV: the
#: previous position and velocity readings (quantised or derived sensors).
A1_HAT, A2_HAT, X3D_PREV, HAS_PREV, SCRATCH, Y_PREV, V_PREV = range(7)
CONTROLLER_MEMORY = 7

#: Slots of the plant's state array: (y, ẏ, P1, P2), the spool (xv, ẋv), the
#: commands received, the previous position and velocity readings (sensors of
#: the plant) and the ring of the last DELAY_RING commands.
XS_XV, XS_WV, XS_COUNT, XS_YPREV, XS_VPREV, XS_RING = 4, 5, 6, 7, 8, 9
PLANT_STATE = XS_RING + DELAY_RING


def plant_state(x0) -> np.ndarray:
    """The plant's state array at (y, ẏ, P1, P2) = ``x0``: spool centred and at
    rest, no command received (the ring zeroed)."""
    x = np.zeros(PLANT_STATE)
    x[:4] = x0[:4]
    return x


def scratch() -> np.ndarray:
    """A float64[1] through which the bytes of one value pass."""
    return np.zeros(1)


# --- plant --------------------------------------------------------------------

@njit(**KERNEL)
def encode_state(x, ap, sample, step_ns, state, clock, scr):
    """State x = (y, ẏ, P1, P2) of ``sample`` into the state and clock messages."""
    sb = scr.view(np.uint8)
    ns = sample * step_ns
    put_stamp(state, ns)
    put_stamp(clock, ns)
    values = joint_state(x[0], x[1], x[2], x[3], ap)
    for k in range(9):
        put_f64(state, _STATE_V[k], values[k], scr, sb)


@njit(**KERNEL)
def plant_sample(x, u, pp, dt, y_limit, sample, step_ns, state, clock, scr):
    """Advance the plant's state array x (:func:`plant_state`) in place by one
    step of the plant of plant array ``pp`` with valve command u [m] and encode
    the new state as sample ``sample`` (the next index). A plant of reference
    structure steps as the episode kernel's reference path; any other as its
    general path: u goes into the ring, the plant gets the command of
    pp[DELAY] commands earlier (a reference plant reads and writes x[:5]
    only, as before the options). Returns True if it diverged."""
    if pp[STRUCTURE] == STRUCTURE_REFERENCE:
        y, v, p1, p2, sv = valve_plant_step(x[0], x[1], x[2], x[3], x[4], u, pp, dt)
    else:
        c = int(x[XS_COUNT])
        x[XS_RING + c % DELAY_RING] = u
        x[XS_COUNT] = c + 1
        d = pp[DELAY]
        n = int(d)
        applied = x[XS_RING + (c + DELAY_RING - n) % DELAY_RING]
        if d != n:                           # a fraction f of a sample: (1 − f)·u(c − n) + f·u(c − n − 1)
            f = d - n
            applied = (1.0 - f) * applied + f * x[XS_RING + (c + DELAY_RING - n - 1) % DELAY_RING]
        y, v, p1, p2, sv, wv = spool_plant_step(x[0], x[1], x[2], x[3], x[4], x[XS_WV], applied, pp, dt)
        x[XS_WV] = wv
    x[0] = y
    x[1] = v
    x[2] = p1
    x[3] = p2
    x[4] = sv
    encode_state(x, pp, sample, step_ns, state, clock, scr)
    return diverged(y, v, p1, p2, y_limit)


@njit(**KERNEL)
def encode_measured(x, ap, sample, step_ns, sp, seed, state, clock, scr):
    """The sensors' readings of state x (:func:`plant_state`) of ``sample``: x plus
    the measurement noise of that sample (sensor array ``sp``, ``seed``; the
    values the episode kernel adds for the law), quantised and with a derived
    velocity when ``sp`` asks (the previous readings kept in x; call once a
    sample), into the state message."""
    n1, n2, n3, n4 = measurement_noise(sp, seed, sample)
    if sensors_on(sp):
        m1, m2, m3, m4 = sensor_readings(x[0], x[1], x[2], x[3], n1, n2, n3, n4, noise_on(sp), sp, x[XS_YPREV],
                                         x[XS_VPREV], sample > 0, step_ns / 1e9)
        x[XS_YPREV] = m1
        x[XS_VPREV] = m2
        encode_state((m1, m2, m3, m4), ap, sample, step_ns, state, clock, scr)
        return
    encode_state((x[0] + n1, x[1] + n2, x[2] + n3, x[3] + n4), ap, sample, step_ns, state, clock, scr)


@njit(**KERNEL)
def command_of(data, step_ns, scr):
    """(sample index or MALFORMED/NOT_FINITE, u [m]) of a command message."""
    if not matches(data, _COMMAND_T, _COMMAND_FIXED):
        return MALFORMED, 0.0
    i = sample_of_stamp(data, step_ns)
    if i < 0:
        return MALFORMED, 0.0
    u = get_f64(data, _COMMAND_V[0], scr, scr.view(np.uint8))
    if not math.isfinite(u):
        return NOT_FINITE, 0.0
    return i, u


# --- controller ----------------------------------------------------------------

@njit(**KERNEL)
def controller_sample(data, mem, gains, ap, cp, rp, sp, seed, dt, step_ns, command, internals, ref, trace):
    """Answer one state message: the command (stamped like the state), the
    internals [t, e1, e2, e3, â1, â2, x1d] and the reference [t, x1d, ẋ1d, ẍ1d,
    x1d⁽³⁾], then adapt ``mem`` (â1, â2, x3d of the previous sample). The law
    reads the state plus the measurement noise of sample i (sensor array
    ``sp``, ``seed``; none when ``sp`` is all 0), as the episode kernel does.

    Writes row i of ``trace`` (the episode's TRACE_COLUMNS: the state as
    received, the true e1 = x1d − y) when i < len(trace).
    Returns the sample index i, or MALFORMED / NOT_FINITE (nothing written).
    """
    if not matches(data, _STATE_T, _STATE_FIXED):
        return MALFORMED
    i = sample_of_stamp(data, step_ns)
    if i < 0:
        return MALFORMED
    scr = mem[SCRATCH:SCRATCH + 1]
    sb = scr.view(np.uint8)
    x1 = get_f64(data, _STATE_V[0], scr, sb)       # position[0] = y
    x2 = get_f64(data, _STATE_V[3], scr, sb)       # velocity[0] = ẏ
    p1 = get_f64(data, _STATE_V[7], scr, sb)       # effort[1] = P1
    p2 = get_f64(data, _STATE_V[8], scr, sb)       # effort[2] = P2
    if not (math.isfinite(x1) and math.isfinite(x2) and math.isfinite(p1) and math.isfinite(p2)):
        return NOT_FINITE
    t = i * dt
    r0, r1, r2, r3 = reference(rp, t)
    a1_hat = mem[A1_HAT]
    a2_hat = mem[A2_HAT]
    m1, m2, m3, m4 = x1, x2, p1, p2
    noisy = noise_on(sp)
    if noisy:
        n1, n2, n3, n4 = measurement_noise(sp, seed, i)
        m1, m2, m3, m4 = x1 + n1, x2 + n2, p1 + n3, p2 + n4
    if sensors_on(sp):
        n1, n2, n3, n4 = measurement_noise(sp, seed, i) if noisy else (0.0, 0.0, 0.0, 0.0)
        m1, m2, m3, m4 = sensor_readings(x1, x2, p1, p2, n1, n2, n3, n4, noisy, sp, mem[Y_PREV], mem[V_PREV],
                                         i > 0, dt)
        mem[Y_PREV] = m1
        mem[V_PREV] = m2
    u, e1, e2, e3, rate1, rate2, x3d = abc_law(
        m1, m2, m3, m4, a1_hat, a2_hat, mem[X3D_PREV], mem[HAS_PREV] > 0.0,
        r0, r1, r2, r3, gains[0], gains[1], gains[2], ap, cp, dt)
    for k in range(4, 12):
        command[k] = data[k]                        # the stamp of the state it answers
    put_f64(command, _COMMAND_V[0], u, scr, sb)
    row = (t, e1, e2, e3, a1_hat, a2_hat, r0)
    for k in range(7):
        put_f64(internals, _INTERNALS_V[k], row[k], scr, sb)
    rrow = (t, r0, r1, r2, r3)
    for k in range(5):
        put_f64(ref, _REFERENCE_V[k], rrow[k], scr, sb)
    if i < trace.shape[0]:
        put_trace_row(trace[i], t, r0, x1, x2, p1, p2, u, r0 - x1, e2, e3, a1_hat, a2_hat)
    mem[A1_HAT], mem[A2_HAT] = adapt(a1_hat, a2_hat, rate1, rate2, cp, dt)
    mem[X3D_PREV] = x3d
    mem[HAS_PREV] = 1.0
    return i


def warm_up() -> None:
    """Compile (or load from the cache) every sample function the nodes call,
    for the argument types they pass (test/test_cold_cache.py checks that a
    node's first samples add none), before anything joins the graph (and,
    in ``has-control stack``, while Ctrl-C still ends the process quietly)."""
    cfg = Config()
    arr = EpisodeArrays.from_config(cfg)
    step_ns = cfg.episode.step_ns
    state, clock, scr = STATE_LAYOUT.buffer(), CLOCK_LAYOUT.buffer(), scratch()
    x = plant_state(arr.x0)
    encode_state(x, arr.plant, 0, step_ns, state, clock, scr)
    plant_sample(x, 0.0, arr.plant, cfg.episode.step, cfg.episode.y_limit, 1, step_ns, state, clock, scr)
    encode_measured(x, arr.plant, 1, step_ns, arr.sensor, arr.seed, state, clock, scr)
    command = COMMAND_LAYOUT.buffer()
    # serialized bytes (the has_control port, the plant), and the preallocated buffers the
    # ros2_control port encodes a state into and reads its command from
    for data in (bytes(state), state):
        controller_sample(data, np.zeros(CONTROLLER_MEMORY), np.array(cfg.gains.as_tuple()), arr.actuator,
                          arr.adaptation, arr.reference, arr.sensor, arr.seed, cfg.episode.step, step_ns,
                          command, CONTROLLER_STATE_LAYOUT.buffer(), REFERENCE_LAYOUT.buffer(),
                          np.zeros((0, len(TRACE_COLUMNS))))
    for data in (bytes(state), command):
        command_of(data, step_ns, scr)
