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
T it is defined after the horizon too. It is tabulated once on the sample
grid (:func:`road_table`, an inverse FFT: O(n log n) for n samples whatever
the cutoff) and looked up by sample in the kernels, so a road costs what a
sine does, plus 32 bytes per sample; the tables of one evaluation are
bounded by :data:`MAX_ROAD_BYTES`, checked before any is built.
"""
from __future__ import annotations

import math

import numpy as np

from has_control.core.params import ROAD_CLASSES, Episode, Reference

#: The lower end of ISO 8608's spatial frequency band [cycles/m].
N_MIN = 0.011
#: ISO 8608's reference spatial frequency n0 [cycles/m].
N0 = 0.1


#: Bytes of a road's table per sample: x1d and its three derivatives, float64.
TABLE_BYTES_PER_SAMPLE = 32
#: The most memory the road tables of one evaluation may take together [bytes]
#: (1 GiB: about 1 000 road scenarios of 10 s at the shipped step of 0.3 ms);
#: a scenario set, horizon or step beyond it is refused before any table is built.
MAX_ROAD_BYTES = 1 << 30


def _harmonics(ref: Reference, period: float) -> np.ndarray:
    """The harmonic numbers k (f_k = k/period) in the band."""
    df = 1.0 / period
    low = max(N_MIN * ref.speed, df)
    if low > ref.cutoff:                       # no harmonic in the band (and no huge or infinite k to count to)
        return np.arange(0)
    return np.arange(math.ceil(low / df - 1e-9), math.floor(ref.cutoff / df + 1e-9) + 1)


def road_components(ref: Reference, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f_k [Hz], A_k [m], φ_k [rad]) of the profile for one period [s]."""
    df = 1.0 / period
    f = _harmonics(ref, period) * df
    n = f / ref.speed
    psd = ROAD_CLASSES[ref.road_class] * (n / N0) ** -2 / ref.speed      # G(f) [m²/Hz]
    amplitude = np.sqrt(2.0 * psd * df)
    phase = np.random.default_rng(ref.seed).uniform(0.0, 2.0 * math.pi, len(f))
    return f, amplitude, phase


def road_table(ref: Reference, episode: Episode) -> np.ndarray:
    """(x1d, ẋ1d, ẍ1d, x1d⁽³⁾) at t_i = i·Δt, i = 0 … n−1, as an (n, 4) array.

    On the grid, component k is sin(2π k i/n + φ_k): each column is the
    imaginary part of Σ_k A_k·e^{iφ_k}·(iω_k)^d·e^{2πi k i/n} (d the
    derivative), a real inverse DFT of half a spectrum (``irfft``), so the
    table costs O(n log n) time whatever the number of components (all below
    Nyquist, which the config checks: no aliasing), and 8 bytes per sample
    beyond itself."""
    n = episode.samples
    period = n * episode.step
    k = _harmonics(ref, period)
    _, a, phi = road_components(ref, period)
    w = 2.0 * math.pi * k / period
    out = np.empty((n, 4))
    half = np.zeros(n // 2 + 1, dtype=np.complex128)       # k < n/2: the cutoff is below Nyquist
    base = -0.5j * n * a * np.exp(1j * phi)                 # Im(c·e^{iθ}) = Re(−i·c·e^{iθ}), irfft's 2/n
    for d in range(4):
        half[k] = base * (1j * w) ** d
        out[:, d] = np.fft.irfft(half, n)
    out[:, 0] += ref.offset - float(np.sum(a * np.sin(phi)))
    out[0, 0] = ref.offset                     # exactly: every sin(φ_k) − sin(φ_k) is 0 at t = 0
    return out


def road_bytes(ref: Reference, episode: Episode) -> int:
    """Memory of the table :func:`road_table` builds [bytes] (0 for another kind)."""
    return episode.samples * TABLE_BYTES_PER_SAMPLE if ref.kind == "road" else 0


def road_rms(ref: Reference, episode: Episode) -> float:
    """The profile's RMS displacement about its mean [m]: √(Σ A_k²/2)."""
    _, a, _ = road_components(ref, episode.samples * episode.step)
    return float(np.sqrt(np.sum(a * a) / 2.0))
