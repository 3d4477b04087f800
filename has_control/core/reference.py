"""Reference trajectories x1d(t) [m] with analytic derivatives up to the third.

Kinds (see :class:`has_control.core.params.Reference`): zero, sine (SPEC §4 default,
0.11·sin 2t), step (septic smooth step, C³), chirp (linear frequency sweep),
road (an ISO 8608 profile, :mod:`has_control.core.road`, defined on the sample
grid and periodic after it).
"""
from __future__ import annotations

import math
import threading
from collections import OrderedDict

import numpy as np
from numba import njit

from has_control.common.errors import ConfigError
from has_control.core.jit import INLINE, KERNEL
from has_control.core.params import (
    REF_AMPLITUDE, REF_CHIRP, REF_F0, REF_F1, REF_KIND, REF_OFFSET, REF_OMEGA, REF_RISE, REF_ROAD, REF_ROWS,
    REF_SINE, REF_STEP, REF_SWEEP, REF_T0, REF_GRID_STEP, Episode, Reference,
)
from has_control.core.road import MAX_ROAD_BYTES, SUM_TERMS_MAX, road_array, road_at, road_bytes, road_terms


@njit(**INLINE)
def reference(rp, t):
    """(x1d, ẋ1d, ẍ1d, x1d⁽³⁾) at time t [s] for the reference array rp.

    A road is defined on its grid t = i·step: t is rounded to the nearest
    sample, and the road repeats after the grid's last sample."""
    kind = int(rp[REF_KIND])
    if kind == REF_ROAD:
        return road_at(rp, int(math.floor(t / rp[REF_GRID_STEP] + 0.5)) % int(rp[REF_ROWS]))
    a = rp[REF_AMPLITUDE]
    off = rp[REF_OFFSET]
    if kind == REF_SINE:
        w = rp[REF_OMEGA]
        s = math.sin(w * t)
        c = math.cos(w * t)
        return off + a * s, a * w * c, -a * w * w * s, -a * w * w * w * c
    if kind == REF_STEP:
        rise = rp[REF_RISE]
        tau = t - rp[REF_T0]
        if tau < 0.0:
            return off, 0.0, 0.0, 0.0
        if rise <= 0.0 or tau >= rise:
            return off + a, 0.0, 0.0, 0.0
        z = tau / rise
        z2 = z * z
        z3 = z2 * z
        z4 = z3 * z
        s0 = z4 * (35.0 - 84.0 * z + 70.0 * z2 - 20.0 * z3)
        s1 = z3 * (140.0 - 420.0 * z + 420.0 * z2 - 140.0 * z3)
        s2 = z2 * (420.0 - 1680.0 * z + 2100.0 * z2 - 840.0 * z3)
        s3 = z * (840.0 - 5040.0 * z + 8400.0 * z2 - 4200.0 * z3)
        return off + a * s0, a * s1 / rise, a * s2 / (rise * rise), a * s3 / (rise * rise * rise)
    if kind == REF_CHIRP:
        f0 = rp[REF_F0]
        k = (rp[REF_F1] - f0) / rp[REF_SWEEP]
        two_pi = 2.0 * math.pi
        phi = two_pi * (f0 * t + 0.5 * k * t * t)
        w = two_pi * (f0 + k * t)
        dw = two_pi * k
        s = math.sin(phi)
        c = math.cos(phi)
        return (off + a * s, a * c * w, a * (-s * w * w + c * dw),
                a * (-c * w * w * w - 3.0 * s * w * dw))
    return off, 0.0, 0.0, 0.0


@njit(**KERNEL)
def reference_series(rp, t):
    """The reference over a whole time array: row i is (x1d [m], ẋ1d [m/s],
    ẍ1d [m/s²], x1d⁽³⁾ [m/s³]) at t[i] [s], :func:`reference`'s bits (one
    compiled loop instead of a Python call per sample: the bag writer, the bag
    readers and the node stack all take the reference from here)."""
    out = np.empty((t.shape[0], 4))
    for i in range(t.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = reference(rp, t[i])
    return out


#: The road reference arrays kept between evaluations [bytes]: every
#: evaluation of a swarm iteration asks for the same ones. Bounded by
#: bytes, not by count: a count of 32 made 33 road scenarios rebuild every
#: table on every call.
ROAD_CACHE_BYTES = 512 << 20
#: What an entry costs beyond its array [bytes]: its key (a Reference and an
#: Episode) and the array object; it dominates for a summed road (384 bytes).
ROAD_ENTRY_BYTES = 1024
_road_cache: OrderedDict = OrderedDict()
_road_cache_bytes = [0]            # the entries' arrays plus ROAD_ENTRY_BYTES each, kept as they come and go
_road_cache_lock = threading.Lock()


def _road_array(ref: Reference, episode: Episode) -> np.ndarray:
    """:func:`has_control.core.road.road_array` of (reference, grid), built
    once while it stays in the cache (least recently used out first). The
    array is shared: the kernels only read it."""
    key = (ref, episode)
    with _road_cache_lock:
        if key in _road_cache:
            _road_cache.move_to_end(key)
            return _road_cache[key]
    array = road_array(ref, episode)
    with _road_cache_lock:
        if key not in _road_cache:                 # (another thread may have built it meanwhile)
            _road_cache[key] = array
            _road_cache_bytes[0] += array.nbytes + ROAD_ENTRY_BYTES
        while _road_cache_bytes[0] > ROAD_CACHE_BYTES and len(_road_cache) > 1:
            _, dropped = _road_cache.popitem(last=False)
            _road_cache_bytes[0] -= dropped.nbytes + ROAD_ENTRY_BYTES
    return array


def road_cached(ref: Reference, episode: Episode) -> bool:
    """Is the road array of (reference, grid) built already (:func:`reference_array` returns at once)?"""
    with _road_cache_lock:
        return (ref, episode) in _road_cache


def check_road_memory(pairs, where: str = "scenarios") -> None:
    """Refuse, before any road array is built, road references whose arrays
    together (distinct (reference, episode) pairs) would take more than
    :data:`has_control.core.road.MAX_ROAD_BYTES`; one line naming ``where``."""
    need = sum(road_bytes(r, e) for r, e in set(pairs))
    if need > MAX_ROAD_BYTES:
        tabulated = sum(1 for r, e in set(pairs) if r.kind == "road" and road_terms(r, e) > SUM_TERMS_MAX)
        raise ConfigError(f"{where}: {tabulated} tabulated road references would take {need / 2**20:,.0f} MiB of "
                          f"tables, more than the limit of {MAX_ROAD_BYTES / 2**20:,.0f} MiB (a road of more than "
                          f"{SUM_TERMS_MAX} components is tabulated, 32 bytes per sample): fewer road scenarios, "
                          "a lower reference.cutoff, a shorter simulation.horizon or a longer simulation.step")


def reference_array(ref: Reference, episode: Episode) -> np.ndarray:
    """The array :func:`reference` reads: the header of ``ref``, and for a
    road its components or its table on ``episode``'s grid
    (:func:`has_control.core.road.road_array`), shared with other callers."""
    if ref.kind != "road":
        return ref.as_array()
    return _road_array(ref, episode)
