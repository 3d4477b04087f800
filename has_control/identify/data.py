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

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
from numba import njit

from has_control.bag.base import warn
from has_control.bag.read import read_bag
from has_control.common.errors import HasControlError
from has_control.core.jit import KERNEL
from has_control.core.noise import measurement_noise
from has_control.core.params import Config, Noise
from has_control.wire import cdr
from has_control.wire.topics import COMMAND, COMMAND_NAMES, JOINT_STATE, STATE, STATE_NAMES

#: Fewest samples an experiment may have (0.3 s at the reference step): below
#: this there are too few segments to estimate anything.
MIN_SAMPLES = 1000


class IdentificationError(HasControlError):
    """Input identification cannot use, or a fit that failed (one line)."""


@dataclass(frozen=True)
class Experiment:
    """One recorded run: measured states x (n, 4) = (y, ẏ, P1, P2) [m, m/s,
    Pa, Pa], commands u (n,) [m], on a grid of ``cfg.episode.step`` [s]
    from sample ``first`` (the plant starts its valve centred at sample 0)."""

    name: str
    x: np.ndarray
    u: np.ndarray
    cfg: Config
    first: int = 0

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
                        on_warning: Callable[[str], None] = warn) -> Experiment:
    """The experiment recorded in the bag at ``path`` (directory or .mcap).

    States and commands are paired by their header stamps (the command is
    stamped with the state it answers); the bag's parameters (custom data)
    give the configuration, else the shipped files, each overridden by
    ``overrides``. Raises :class:`IdentificationError` or BagError naming
    the bag and what is missing.
    """
    bag = read_bag(path, topics=None, on_warning=on_warning)
    st, cm = bag.find(STATE, JOINT_STATE), bag.find(COMMAND, JOINT_STATE)
    states, commands = bag.messages.get(st, []), bag.messages.get(cm, [])
    if not states or not commands:
        empty = [t for t, m in ((st, states), (cm, commands)) if not m]
        raise IdentificationError(f"{path}: no messages on {', '.join(empty)}")
    cfg = bag.config(overrides)
    step_ns = cfg.episode.step_ns
    names, pos, vel, eff = _joint_states(states, f"{path}: {st}")
    if names != STATE_NAMES or pos.shape[1] != 3 or vel.shape[1] != 3 or eff.shape[1] != 3:
        raise IdentificationError(f"{path}: {st}: joints {names} are not this actuator's {STATE_NAMES} "
                                  "(position, velocity, effort of 3 each): a bag of another model")
    cnames, cpos, _, _ = _joint_states(commands, f"{path}: {cm}")
    if cnames != COMMAND_NAMES or cpos.shape[1] != 1:
        raise IdentificationError(f"{path}: {cm}: joints {cnames} are not the valve command {COMMAND_NAMES}: "
                                  "a bag of another model")
    xs = _by_sample(cdr.stamps_ns([d for _, d in states]), step_ns, st, path)
    us = _by_sample(cdr.stamps_ns([d for _, d in commands]), step_ns, cm, path)
    x = np.column_stack([pos[:, 0], vel[:, 0], eff[:, 1], eff[:, 2]])
    common = sorted(set(xs) & set(us))
    if not common:
        raise IdentificationError(f"{path}: no command answers a recorded state (their stamps never match)")
    first = common[0]
    end = next((k for k, i in enumerate(common) if i != first + k), len(common))
    rows = np.array([xs[i] for i in common[:end]])
    cols = np.array([us[i] for i in common[:end]])
    xx, uu = x[rows], cpos[cols, 0]
    good = np.isfinite(xx).all(axis=1) & np.isfinite(uu) & (np.abs(xx[:, 0]) <= cfg.episode.y_limit)
    stop = int(np.argmin(good)) if not good.all() else len(good)
    if stop < MIN_SAMPLES:
        raise IdentificationError(f"{path}: {stop} usable samples of state and command in a row; "
                                  f"identification needs at least {MIN_SAMPLES}")
    return Experiment(str(path), np.ascontiguousarray(xx[:stop]), np.ascontiguousarray(uu[:stop]), cfg, first)


def _joint_states(messages, what: str):
    try:
        return cdr.joint_states([d for _, d in messages], what)
    except (HasControlError, ValueError, IndexError) as exc:
        raise IdentificationError(f"{what}: not readable as sensor_msgs/JointState ({exc})") from None


def _by_sample(stamps: np.ndarray, step_ns: int, topic: str, path) -> dict[int, int]:
    """Sample number -> index of its first message (a state sent again is one sample)."""
    idx = np.rint(stamps / step_ns).astype(np.int64)
    if len(idx) and np.abs(stamps - idx * step_ns).max() > step_ns // 100:
        raise IdentificationError(f"{path}: {topic}: header stamps are not on the sample grid of "
                                  f"{step_ns * 1e-9:g} s (simulation.step; set it with --config)")
    out: dict[int, int] = {}
    for k, i in enumerate(idx.tolist()):
        out.setdefault(i, k)
    return out


@njit(**KERNEL)
def _noise_table(sp, seed, first, n, out):
    for i in range(n):
        n1, n2, n3, n4 = measurement_noise(sp, seed, first + i)
        out[i, 0] = n1
        out[i, 1] = n2
        out[i, 2] = n3
        out[i, 3] = n4


def measured(x: np.ndarray, noise: Noise, first: int = 0) -> np.ndarray:
    """States ``x`` (n, 4) as sensors with ``noise`` read them: plus the core's
    seeded noise of samples first .. first + n − 1, the values the controller
    reads (:func:`has_control.core.noise.measurement_noise`)."""
    table = np.zeros((len(x), 4))
    sp = noise.as_array()
    if sp.any():
        _noise_table(sp, int(noise.seed), first, len(x), table)
    return np.asarray(x, dtype=np.float64) + table


def experiment_from_trace(trace, cfg: Config, noise: Noise | None = None, name: str = "simulated") -> Experiment:
    """An experiment from a core trace (:func:`has_control.core.episode.simulate`):
    its true states read through ``noise`` (default ``cfg.noise``), and its commands."""
    x = np.column_stack([trace["y"], trace["ydot"], trace["P1"], trace["P2"]])
    xm = measured(x, cfg.noise if noise is None else noise)
    return Experiment(name, np.ascontiguousarray(xm), np.ascontiguousarray(trace["u"]), cfg)
