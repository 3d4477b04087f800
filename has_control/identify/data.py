"""Experiments: what identification reads from a recorded run, one row per sample.

An experiment is the measured state (y [m], ẏ [m/s], P1 [Pa], P2 [Pa]) and
the valve command u [m] applied at each sample, on a grid of step Δt [s],
with the run's configuration (the controller's model ``actuator.*``, the
plant's known options, the controller and reference that ran). It comes from
a bag (``state`` and ``command`` topics, sensor_msgs/JointState in the
layout of :mod:`has_control.wire.topics`, under any namespace; written by
``stack --record``, the recorder node, or ``ros2 bag record`` and
``rosbags-convert``) or, for studies and tests, from a simulated trace with
the core's seeded measurement noise added, which is what a plant node that
publishes measured states records.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
from numba import njit

from has_control.bag.base import BagError, warn
from has_control.bag.recorded import Reading, layout_of, read_recording, read_run_bag
from has_control.common.errors import HasControlError
from has_control.core.jit import KERNEL
from has_control.core.noise import measurement_noise, noise_on, sensor_readings
from has_control.core.params import Config, Noise
from has_control.wire.joint_mapping import DEFAULT_COMMAND_TOPIC
from has_control.wire.topics import COMMAND, FLOAT64_ARRAY, JOINT_STATE

#: Fewest samples an experiment may have (0.3 s at the reference step): below
#: this there are too few segments to estimate anything.
MIN_SAMPLES = 1000


class IdentificationError(HasControlError):
    """Input identification cannot use, or a fit that failed (one line)."""


@dataclass(frozen=True)
class Experiment:
    """One recorded run: measured states x (n, 4) = (y, ẏ, P1, P2) [m, m/s,
    Pa, Pa], commands u (n,) [m], on a grid of ``cfg.episode.step`` [s]
    from sample ``first`` (the plant starts its valve centred at sample 0);
    ``gaps``: rows recorded without a usable state and command (holding the
    row before), which no segment may span."""

    name: str
    x: np.ndarray
    u: np.ndarray
    cfg: Config
    first: int = 0
    gaps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # samples without a measurement

    @property
    def samples(self) -> int:
        return len(self.u)

    @property
    def step(self) -> float:
        return self.cfg.episode.step

    @property
    def t(self) -> np.ndarray:
        return (self.first + np.arange(self.samples)) * self.step


def experiment_from_bag(path: str | Path, overrides: Iterable[str | Path] = (),
                        on_warning: Callable[[str], None] = warn, reading: Reading = Reading()) -> Experiment:
    """The experiment recorded in the bag at ``path`` (directory or .mcap).

    States and commands come from :func:`has_control.bag.recorded.read_recording`
    (either layout; stamps from any epoch, jitter within its tolerance,
    repeats collapsed), on the grid of ``simulation.step``; the bag's
    parameters (custom data) give the configuration, else the shipped files,
    each overridden by ``overrides``. The experiment runs from the first to
    the last sample with a finite state and its command, stopping where
    |y| exceeds ``simulation.y_limit`` for good (diverged, said in one line); the
    samples between without one (dropped, non-finite, beyond the limit and back,
    unanswered) are its ``gaps``, said in one line:
    no segment that spans one is fitted. Raises :class:`IdentificationError`
    or BagError naming the bag and what is missing.
    """
    bag = read_run_bag(path, on_warning=on_warning)
    cfg = bag.config(overrides)
    _, _, cm = layout_of(bag, reading)
    if cm is None or not bag.messages.get(cm):
        raise IdentificationError(f"{path}: no messages on a command topic ('…/{COMMAND}' {JOINT_STATE}, or "
                                  f"{DEFAULT_COMMAND_TOPIC} {FLOAT64_ARRAY}); topics: {', '.join(sorted(bag.types))}")
    try:
        rec = read_recording(bag, cfg.episode.step, reading, emit=False)
    except BagError as exc:
        if "another model" in str(exc):
            raise IdentificationError(str(exc)) from None
        raise
    if not rec.command.any():
        raise IdentificationError(f"{path}: no messages on a command topic ('…/{COMMAND}' {JOINT_STATE}, or "
                                  f"{DEFAULT_COMMAND_TOPIC} {FLOAT64_ARRAY}); topics: {', '.join(sorted(bag.types))}")
    usable = rec.state & rec.command & np.isfinite(rec.x).all(axis=1) & np.isfinite(rec.u)
    if not usable.any():
        raise IdentificationError(f"{path}: no command answers a recorded state (their stamps never match)")
    out = rec.state & np.isfinite(rec.x[:, 0]) & (np.abs(rec.x[:, 0]) > cfg.episode.y_limit)
    usable &= ~out
    diverged = ""
    if out.any() and not usable[int(np.flatnonzero(out)[-1]):].any():
        # the run ends beyond the limit (diverged): identified up to there; an excursion the run comes
        # back from is a bad sample (a gap), never a reason to drop the rest
        stop = int(np.flatnonzero(out & ~np.maximum.accumulate(usable[::-1])[::-1])[0])
        usable[stop:] = False
        diverged = (f"{path}: |y| exceeds simulation.y_limit {cfg.episode.y_limit:g} m from t = "
                    f"{stop * cfg.episode.step:.6f} s to the end (the run diverged): identified up to there")
    good = np.flatnonzero(usable)
    if len(good) < MIN_SAMPLES:
        raise IdentificationError(f"{path}: {len(good)} usable samples of state and command; "
                                  f"identification needs at least {MIN_SAMPLES}")
    first, last = int(good[0]), int(good[-1]) + 1
    ok = usable[first:last]
    gaps = np.flatnonzero(~ok)
    keep = np.maximum.accumulate(np.where(ok, np.arange(len(ok)), 0))     # a gap holds the last usable sample
    xx, uu = rec.x[first:last][keep], rec.u[first:last][keep]
    for line in rec.notes + ([diverged] if diverged else []):   # once accepted: a refusal stays one line
        on_warning(line)
    if len(gaps):
        on_warning(f"{path}: {len(gaps)} of {len(ok)} samples from t = {first * cfg.episode.step:.6f} s without "
                   "a finite state and its command (dropped, non-finite, beyond y_limit or unanswered): identify "
                   "leaves out every segment that spans one")
    return Experiment(str(path), np.ascontiguousarray(xx), np.ascontiguousarray(uu), cfg, first,
                      gaps.astype(np.int64))


@njit(**KERNEL)
def _readings(x, sp, seed, first, dt, out):
    """Row i of ``out``: :func:`~has_control.core.noise.sensor_readings` of
    row i of ``x`` at sample first + i, as the controller reads it."""
    noisy = noise_on(sp)
    y_prev = v_prev = 0.0
    for i in range(x.shape[0]):
        n1, n2, n3, n4 = measurement_noise(sp, seed, first + i) if noisy else (0.0, 0.0, 0.0, 0.0)
        m1, m2, m3, m4 = sensor_readings(x[i, 0], x[i, 1], x[i, 2], x[i, 3], n1, n2, n3, n4, noisy, sp,
                                         y_prev, v_prev, first + i > 0, dt)
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = m1, m2, m3, m4
        y_prev, v_prev = m1, m2


def measured(x: np.ndarray, noise: Noise, first: int = 0, step: float = 3.0e-4) -> np.ndarray:
    """States ``x`` (n, 4) as sensors with ``noise`` read them at sample step
    ``step`` [s]: plus the core's seeded noise of samples first .. first + n − 1,
    quantised and with a derived velocity as the sensors say: the values the
    controller reads (:func:`has_control.core.noise.sensor_readings`)."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    sp = noise.as_array(step)
    if not sp.any():
        return x.copy()
    out = np.empty_like(x)
    _readings(x, sp, int(noise.seed), int(first), float(step), out)
    return out


def experiment_from_trace(trace, cfg: Config, noise: Noise | None = None, name: str = "simulated") -> Experiment:
    """An experiment from a core trace (:func:`has_control.core.episode.simulate`):
    its true states read through ``noise`` (default ``cfg.noise``), and its commands."""
    x = np.column_stack([trace["y"], trace["ydot"], trace["P1"], trace["P2"]])
    xm = measured(x, cfg.noise if noise is None else noise, step=cfg.episode.step)
    return Experiment(name, np.ascontiguousarray(xm), np.ascontiguousarray(trace["u"]), cfg)
