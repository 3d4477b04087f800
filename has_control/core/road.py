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
grid (:func:`road_table`) and looked up by sample in the kernels, so a road
costs what a sine does.
"""
from __future__ import annotations

import math

import numpy as np

from has_control.core.params import ROAD_CLASSES, Episode, Reference

#: The lower end of ISO 8608's spatial frequency band [cycles/m].
N_MIN = 0.011
#: ISO 8608's reference spatial frequency n0 [cycles/m].
N0 = 0.1


def road_components(ref: Reference, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(f_k [Hz], A_k [m], φ_k [rad]) of the profile for one period [s]."""
    df = 1.0 / period
    low = max(N_MIN * ref.speed, df)
    if low > ref.cutoff:                       # no harmonic in the band (and no huge or infinite k to count to)
        k = np.arange(0)
    else:
        k = np.arange(math.ceil(low / df - 1e-9), math.floor(ref.cutoff / df + 1e-9) + 1)
    f = k * df
    n = f / ref.speed
    psd = ROAD_CLASSES[ref.road_class] * (n / N0) ** -2 / ref.speed      # G(f) [m²/Hz]
    amplitude = np.sqrt(2.0 * psd * df)
    phase = np.random.default_rng(ref.seed).uniform(0.0, 2.0 * math.pi, len(f))
    return f, amplitude, phase


def road_table(ref: Reference, episode: Episode) -> np.ndarray:
    """(x1d, ẋ1d, ẍ1d, x1d⁽³⁾) at t_i = i·Δt, i = 0 … n−1, as an (n, 4) array."""
    n = episode.samples
    f, a, phi = road_components(ref, n * episode.step)
    w = 2.0 * math.pi * f
    t = np.arange(n) * episode.step
    out = np.zeros((n, 4))
    out[:, 0] = ref.offset
    for wk, ak, pk in zip(w, a, phi):          # one component at a time: n floats of memory
        s = np.sin(wk * t + pk)
        c = np.cos(wk * t + pk)
        out[:, 0] += ak * (s - math.sin(pk))
        out[:, 1] += ak * wk * c
        out[:, 2] -= ak * wk * wk * s
        out[:, 3] -= ak * wk * wk * wk * c
    return out


def road_rms(ref: Reference, episode: Episode) -> float:
    """The profile's RMS displacement about its mean [m]: √(Σ A_k²/2)."""
    _, a, _ = road_components(ref, episode.samples * episode.step)
    return float(np.sqrt(np.sum(a * a) / 2.0))
