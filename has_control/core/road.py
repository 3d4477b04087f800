"""A road-like reference: an ISO 8608 random road profile, as the actuator would follow it.

ISO 8608 classifies roads by the displacement PSD of their elevation over
spatial frequency n [cycles/m]: Gd(n) = Gd(n0)·(n/n0)^−2 with n0 = 0.1
cycles/m and Gd(n0) from 16e-6 m³ (class A) to 4096e-6 m³ (class E),
:data:`~has_control.core.params.ROAD_CLASSES`. Driven at speed v [m/s], the
profile is a signal of time with f = n·v [Hz] and one-sided PSD
G(f) = Gd(f/v)/v.

The profile is the usual harmonic superposition, one period of it per
episode: with T = n_samples·Δt, components at the harmonics f_k = k/T from
the band's lower edge max(n_min·v, 1/T) (ISO's n_min = 0.011 cycles/m) up to
``cutoff`` [Hz] (the band the actuator can follow; nothing above it: a
brick-wall low-pass), amplitudes A_k = √(2·G(f_k)/T) and phases drawn
uniformly from ``seed``:

    x1d(t) = offset + Σ_k A_k·(sin(2π f_k t + φ_k) − sin φ_k)

(it starts at ``offset``, where the actuator rests). Its derivatives are
analytic, so x1d⁽³⁾ exists for the back-stepping law, and being periodic in
T it is defined after the horizon too. It is defined on the sample grid
t_i = i·Δt, where component k is sin(2π k i/n + φ_k), and computed one of
two ways (:func:`road_array` picks by the number of components K):

* **summed in the kernel** (K ≤ :data:`SUM_TERMS_MAX`, which covers the
  shipped 2 Hz cutoff, 17 components for 10 s): the array holds the K
  complex amplitudes A_k·e^{iφ_k}, 16 bytes each, and :func:`road_at` sums
  them at each sample (two sin/cos and K complex products: the harmonics
  are powers of e^{2πi·i/n}). A 10 s road is 384 bytes, a sine 112.
* **tabulated** (more components): (x1d, ẋ1d, ẍ1d, x1d⁽³⁾) on the whole
  grid, an inverse FFT (O(n log n) whatever the cutoff), 32 bytes per
  sample; the arrays of one evaluation are bounded by
  :data:`MAX_ROAD_BYTES`, checked before any is built.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from has_control.core.jit import INLINE, KERNEL
from has_control.core.params import (
    N_REFERENCE, REF_BIAS, REF_FIRST, REF_OFFSET, REF_ROWS, REF_GRID_STEP, REF_TERMS, ROAD_CLASSES, Episode,
    Reference,
)

#: The lower end of ISO 8608's spatial frequency band [cycles/m].
N_MIN = 0.011
#: ISO 8608's reference spatial frequency n0 [cycles/m].
N0 = 0.1


#: Bytes of a road's table per sample: x1d and its three derivatives, float64.
TABLE_BYTES_PER_SAMPLE = 32
#: Bytes of a summed road per component: A_k·e^{iφ_k}, two float64.
TERM_BYTES = 16
#: The most components a road sums in the kernel at each sample; a road with
#: more is tabulated. Summing costs a few ns per component per sample, once
#: per block of candidates in the batch kernel (``scripts/bench --scenarios``;
#: the figures are in docs/speed.md).
SUM_TERMS_MAX = 64
#: The most memory the road arrays of one evaluation may take together [bytes]
#: (1 GiB: about 1 000 tabulated road scenarios of 10 s at the shipped step of 0.3 ms);
#: a scenario set, horizon or step beyond it is refused before any table is built.
MAX_ROAD_BYTES = 1 << 30


def _band(ref: Reference, period: float) -> tuple[int, int]:
    """The first and one past the last harmonic number k (f_k = k/period) in the band."""
    df = 1.0 / period
    low = max(N_MIN * ref.speed, df)
    if low > ref.cutoff:                       # no harmonic in the band (and no huge or infinite k to count to)
        return 0, 0
    return math.ceil(low / df - 1e-9), math.floor(ref.cutoff / df + 1e-9) + 1


def _harmonics(ref: Reference, period: float) -> np.ndarray:
    """The harmonic numbers k (f_k = k/period) in the band."""
    return np.arange(*_band(ref, period))


def road_components(ref: Reference, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f_k [Hz], A_k [m], φ_k [rad]) of the profile for one period [s]."""
    df = 1.0 / period
    f = _harmonics(ref, period) * df
    n = f / ref.speed
    psd = ROAD_CLASSES[ref.road_class] * (n / N0) ** -2 / ref.speed      # G(f) [m²/Hz]
    amplitude = np.sqrt(2.0 * psd * df)
    phase = np.random.default_rng(ref.seed).uniform(0.0, 2.0 * math.pi, len(f))
    return f, amplitude, phase


def road_terms(ref: Reference, episode: Episode) -> int:
    """How many components the road has on ``episode``'s grid (one period)."""
    first, end = _band(ref, episode.samples * episode.step)
    return max(end - first, 0)


def _fft_table(n: int, period: float, k: np.ndarray, a: np.ndarray, phi: np.ndarray, offset: float,
               bias: float) -> np.ndarray:
    """(x1d, ẋ1d, ẍ1d, x1d⁽³⁾) at t_i = i·Δt, i = 0 … n−1, as an (n, 4) array.

    On the grid, component k is sin(2π k i/n + φ_k): each column is the
    imaginary part of Σ_k A_k·e^{iφ_k}·(iω_k)^d·e^{2πi k i/n} (d the
    derivative), a real inverse DFT of half a spectrum (``irfft``), so the
    table costs O(n log n) time whatever the number of components (all below
    Nyquist, which the config checks: no aliasing), and 8 bytes per sample
    beyond itself. Harmonics ``k``, amplitudes ``a`` [m] and phases ``phi``
    [rad] of :func:`road_components`, ``bias`` = Σ_k A_k·sin φ_k [m]."""
    w = 2.0 * math.pi * k / period
    out = np.empty((n, 4))
    half = np.zeros(n // 2 + 1, dtype=np.complex128)       # k < n/2: the cutoff is below Nyquist
    base = -0.5j * n * a * np.exp(1j * phi)                 # Im(c·e^{iθ}) = Re(−i·c·e^{iθ}), irfft's 2/n
    for d in range(4):
        half[k] = base * (1j * w) ** d
        out[:, d] = np.fft.irfft(half, n)
    out[:, 0] += offset - bias
    out[0, 0] = offset                         # exactly: every sin(φ_k) − sin(φ_k) is 0 at t = 0
    return out


def road_array(ref: Reference, episode: Episode) -> np.ndarray:
    """The reference array of a road on ``episode``'s grid: the header of
    ``ref`` (grid, components, bias Σ A_k·sin φ_k), then the components
    A_k·e^{iφ_k} as (re, im) pairs if there are at most
    :data:`SUM_TERMS_MAX`, else the table (:func:`_fft_table`; REF_TERMS −1)."""
    n = episode.samples
    period = n * episode.step
    k = _harmonics(ref, period)
    _, a, phi = road_components(ref, period)
    head = ref.as_array()
    head[REF_ROWS] = n
    head[REF_GRID_STEP] = episode.step
    head[REF_BIAS] = bias = float(np.sum(a * np.sin(phi)))
    if len(k) <= SUM_TERMS_MAX:
        head[REF_TERMS] = len(k)
        head[REF_FIRST] = k[0] if len(k) else 0
        terms = np.empty((len(k), 2))
        terms[:, 0] = a * np.cos(phi)
        terms[:, 1] = a * np.sin(phi)
        return np.concatenate([head, terms.ravel()])
    head[REF_TERMS] = -1
    return np.concatenate([head, _fft_table(n, period, k, a, phi, ref.offset, bias).ravel()])


@njit(**INLINE)
def road_at(rp, i):
    """(x1d, ẋ1d, ẍ1d, x1d⁽³⁾) of the road array ``rp`` at grid sample i,
    0 ≤ i < rp[REF_ROWS]: its table row, or the sum of its components.

    Summed: with z = e^{2πi·i/n}, component k is Im(c_k·z^k) and its
    derivatives ω_k·Re, −ω_k²·Im, −ω_k³·Re (ω_k = 2πk/T); z^{k0} is one
    sin/cos of an exact integer angle, each next harmonic one product by z."""
    terms = int(rp[REF_TERMS])
    rows = int(rp[REF_ROWS])
    if terms < 0:
        j = N_REFERENCE + 4 * i
        return rp[j], rp[j + 1], rp[j + 2], rp[j + 3]
    first = int(rp[REF_FIRST])
    step_angle = 2.0 * math.pi / rows
    zr = math.cos(step_angle * i)
    zi = math.sin(step_angle * i)
    angle = step_angle * ((first * i) % rows)
    pr = math.cos(angle)
    pj = math.sin(angle)
    w1 = step_angle / rp[REF_GRID_STEP]                  # 2π/T [rad/s]
    x = v = a = jerk = 0.0
    for m in range(terms):
        cr = rp[N_REFERENCE + 2 * m]
        ci = rp[N_REFERENCE + 2 * m + 1]
        re = cr * pr - ci * pj
        im = cr * pj + ci * pr
        w = w1 * (first + m)
        w2 = w * w
        x += im
        v += w * re
        a -= w2 * im
        jerk -= w2 * w * re
        pr, pj = pr * zr - pj * zi, pr * zi + pj * zr
    if i == 0:
        return rp[REF_OFFSET], v, a, jerk          # exactly: every sin(φ_k) − sin(φ_k) is 0 at t = 0
    return rp[REF_OFFSET] - rp[REF_BIAS] + x, v, a, jerk


@njit(**KERNEL)
def _tabulate(rp, out):
    """Row i of ``out`` = :func:`road_at` (rp, i)."""
    for i in range(out.shape[0]):
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = road_at(rp, i)


def road_table(ref: Reference, episode: Episode) -> np.ndarray:
    """(x1d, ẋ1d, ẍ1d, x1d⁽³⁾) at t_i = i·Δt, i = 0 … n−1, as an (n, 4)
    array: what the kernels read at each sample, however the road is held."""
    out = np.empty((episode.samples, 4))
    _tabulate(road_array(ref, episode), out)
    return out


def road_bytes(ref: Reference, episode: Episode) -> int:
    """Memory of what :func:`road_array` puts after the header [bytes]:
    16 per component summed, 32 per sample tabulated (0 for another kind)."""
    if ref.kind != "road":
        return 0
    terms = road_terms(ref, episode)
    return terms * TERM_BYTES if terms <= SUM_TERMS_MAX else episode.samples * TABLE_BYTES_PER_SAMPLE


def road_rms(ref: Reference, episode: Episode) -> float:
    """The profile's RMS displacement about its mean [m]: √(Σ A_k²/2)."""
    _, a, _ = road_components(ref, episode.samples * episode.step)
    return float(np.sqrt(np.sum(a * a) / 2.0))
