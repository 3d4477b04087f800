"""Seeded measurement noise as a pure function of (seed, sample, channel).

A counter-based generator: the uniform draw of channel k at sample i is
SplitMix64's finaliser applied to the counter 4·i + k under a key made from
the seed, and two uniforms give two standard normals by Box-Muller. Nothing
is carried from sample to sample, so the episode kernel, the batch kernel
(once per sample for all its lanes) and the controller node (on the sample
index of each state's stamp) draw the same values in any order, and a
replayed or resumed run draws them again.

Channels: 0 y [m], 1 ẏ [m/s], 2 P1 [Pa], 3 P2 [Pa], scaled by the standard
deviations of :class:`~has_control.core.params.Noise` (the sensor array).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from has_control.core.jit import INLINE, LEAF
from has_control.core.params import RESOLUTION_P, RESOLUTION_Y, VELOCITY_ALPHA, VELOCITY_DERIVED

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_ULP53 = 1.0 / 9007199254740992.0           # 2^-53
_TWO_PI = 2.0 * math.pi


@njit(**LEAF)
def _mix(z):
    """SplitMix64's finaliser (a bijection of uint64 with full avalanche)."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(**LEAF)
def uniform(seed, i, k):
    """A uniform draw in (0, 1] for channel k of sample i under ``seed`` (integers ≥ 0)."""
    key = _mix(np.uint64(seed) * _GOLDEN + np.uint64(1))
    h = _mix(key ^ ((np.uint64(i) * np.uint64(4) + np.uint64(k)) * _GOLDEN))
    return (float(h >> _S11) + 1.0) * _ULP53


@njit(**LEAF)
def _normal_pair(seed, i, k):
    """Two standard normals (Box-Muller) from the uniforms of channels k, k + 1."""
    r = math.sqrt(-2.0 * math.log(uniform(seed, i, k)))
    a = _TWO_PI * uniform(seed, i, k + 1)
    return r * math.cos(a), r * math.sin(a)


@njit(**LEAF)
def noise_on(sp):
    """Whether the sensor array ``sp`` (array or tuple) asks for any noise."""
    return (sp[0] != 0.0) | (sp[1] != 0.0) | (sp[2] != 0.0) | (sp[3] != 0.0)


@njit(**INLINE)
def measurement_noise(sp, seed, i):
    """The noise (on y [m], ẏ [m/s], P1 [Pa], P2 [Pa]) of sample i: standard
    normals scaled by the sensor array ``sp``'s standard deviations."""
    z0, z1 = _normal_pair(seed, i, 0)
    z2, z3 = _normal_pair(seed, i, 2)
    return sp[0] * z0, sp[1] * z1, sp[2] * z2, sp[3] * z3


@njit(**LEAF)
def sensors_on(sp):
    """Whether the sensor array ``sp`` asks for quantisation or a derived velocity
    (what only the kernels' general path reads)."""
    return (sp[RESOLUTION_Y] != 0.0) | (sp[RESOLUTION_P] != 0.0) | (sp[VELOCITY_DERIVED] != 0.0)


@njit(**LEAF)
def quantised(value, resolution):
    """``value`` rounded to the nearest multiple of ``resolution`` (> 0; ties to even), else as it is."""
    return np.rint(value / resolution) * resolution if resolution > 0.0 else value


@njit(**INLINE)
def sensor_readings(x1, x2, x3, x4, n1, n2, n3, n4, noisy, sp, y_prev, v_prev, has_prev, dt):
    """What the controller reads of the true state (y [m], ẏ [m/s], P1, P2 [Pa]):
    plus the noise n1..n4 when ``noisy``, position and pressures rounded to
    their resolutions, and with a derived velocity the backward difference
    (y_i − y_{i−1})/Δt of the position readings (``y_prev`` the previous one;
    0 at the first sample, filter or not), filtered v_i = v_{i−1} + α(d_i − v_{i−1})
    (``v_prev``; α = 0 stands for unfiltered, v_i = d_i exactly). Returns the four
    readings; the second reading and the position reading are the next
    sample's ``v_prev`` and ``y_prev``."""
    m1 = quantised(x1 + n1 if noisy else x1, sp[RESOLUTION_Y])
    m2 = x2 + n2 if noisy else x2
    m3 = quantised(x3 + n3 if noisy else x3, sp[RESOLUTION_P])
    m4 = quantised(x4 + n4 if noisy else x4, sp[RESOLUTION_P])
    d = (m1 - y_prev) / dt if has_prev else 0.0
    alpha = sp[VELOCITY_ALPHA]
    v = d if (alpha == 0.0) | (not has_prev) else v_prev + alpha * (d - v_prev)
    return m1, v if sp[VELOCITY_DERIVED] != 0.0 else m2, m3, m4
