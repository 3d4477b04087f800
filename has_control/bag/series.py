"""Every recorded signal of a run, on its sample grid, gaps allowed: what a figure of a bag shows.

:func:`~has_control.bag.score.recorded_run` refuses a run that is not one
state and one command per sample (its J would not be the run's);
a figure shows whatever was recorded. State and command are read by
:func:`has_control.bag.recorded.read_recording` (either layout, stamps of any
epoch, jitter within its tolerance, repeats collapsed, drops counted); each
message goes to its nearest sample and NaN is left where a topic has no
message for a sample (a gap in the figure): a realtime run whose controller did not answer every
state, a recording cut short, a bag from another recorder. Only the state
topic is required. The signals, all SI:

* state (``…/state``, or ``/joint_states`` through ``state_interfaces``): y [m], ẏ [m/s], P1, P2 [Pa];
* command (``…/command``, or the ros2_control layout's Float64MultiArray): u [m], the valve command sent;
* reference (``…/controller/reference``; else the x1d of controller_state): x1d [m]; where
  the controller published none and the bag holds the run's parameters, the
  reference they define (so e1 is whole wherever the state is); a bag of
  only state and command: the reference the configuration defines, said in one line;
* controller_state: â1 [N·s/m], â2 [m³/(s·Pa)];
* gains (``…/controller/gains``): (t [s], k1, k2, k3 [1/s]) each time they changed;
* missed samples (``…/plant/missed``, a realtime stack's bag): the samples the
  plant ran without their command (held), and those on the fail-safe (valve
  centred). A bag without this topic does not say; a sample whose command is
  absent from the bag was surely missed (``missing['command']``), one whose
  command came late cannot be told.

A bag without the run's parameters (``rosbags-convert`` drops ``custom_data``)
is read with the configuration files, Δt taken from the state stamps and
the horizon from the recording, with a warning.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from has_control.bag.base import PARAMETERS_KEY, BagError, warn
from has_control.bag.read import Bag
from has_control.bag.recorded import Reading, Recording, read_recording, read_run_bag
from has_control.common.errors import HasControlError
from has_control.config import build_config
from has_control.core.params import Config
from has_control.core.run import Run
from has_control.core.reference import reference_array, reference_series
from has_control.wire import cdr
from has_control.wire.topics import (
    COMMAND, CONTROLLER_STATE, CONTROLLER_STATE_COLUMNS, FLOAT64_ARRAY, GAINS, GAINS_COLUMNS,
    MISSED, MISSED_COLUMNS, REFERENCE, REFERENCE_COLUMNS,
)


@dataclass(frozen=True)
class RunSeries(Run):
    """One recorded run on its sample grid (row i: t = i·Δt); NaN where nothing was recorded."""

    name: str
    cfg: Config
    gains_t: np.ndarray        # [s], when each gain set took effect
    gains: np.ndarray          # (m, 3) [1/s]
    missing: dict[str, np.ndarray]   # topic (relative name) -> samples of the state without a message
    parameters: bool           # the bag carried the run's parameters
    missed: np.ndarray | None = None     # samples a realtime plant ran without their command (None: not recorded)
    failsafe: np.ndarray | None = None   # of those, the samples run with the valve centred

    @property
    def complete(self) -> bool:
        """Every sample of the run has a state, command and reference, and the run is as long as its config."""
        return (len(self.t) >= self.cfg.episode.samples and not any(len(v) for v in self.missing.values()))


def run_series(path: str | Path, overrides: Iterable[str | Path] = (),
               on_warning: Callable[[str], None] = warn, reading: Reading = Reading()) -> RunSeries:
    """The run recorded in the bag at ``path`` (see the module docstring)."""
    bag = read_run_bag(path, on_warning=on_warning)
    return series_of(bag, overrides, reading)


def series_of(bag: Bag, overrides: Iterable[str | Path] = (), reading: Reading = Reading()) -> RunSeries:
    """The run recorded in ``bag`` (already read)."""
    cfg = bag.config(overrides)
    params = PARAMETERS_KEY in bag.custom_data
    rec = read_recording(bag, cfg.episode.step if params else None, reading)
    if not params:
        cfg = _fitted_config(bag, cfg, rec)
    step = rec.step
    grid = _Grid(rec, 1e-3 if params else 0.25)
    n = rec.samples
    have = rec.state
    missing: dict[str, np.ndarray] = {}
    if rec.command_topic is not None:
        missing[COMMAND] = np.flatnonzero(have & ~rec.command)
    x1d = a1 = a2 = np.full(n, math.nan)
    cs = _optional(bag, CONTROLLER_STATE, FLOAT64_ARRAY)
    if cs:
        rows, data = _arrays(bag, cs, CONTROLLER_STATE_COLUMNS, grid)
        c = CONTROLLER_STATE_COLUMNS.index
        a1, a2, x1d = (_on_grid(n, rows, data[:, c(k)]) for k in ("a1_hat", "a2_hat", "x1d"))
    rf = _optional(bag, REFERENCE, FLOAT64_ARRAY)
    if rf:
        rows, data = _arrays(bag, rf, REFERENCE_COLUMNS, grid)
        x1d = _on_grid(n, rows, data[:, REFERENCE_COLUMNS.index("x1d")])
        got = np.zeros(n, bool)
        got[rows[rows < n]] = True
        missing[REFERENCE] = np.flatnonzero(have & ~got)
    elif not cs:
        src = f"{PARAMETERS_KEY} of the bag" if params else "the configuration files"
        bag.on_warning(f"{bag.path}: no '…/{REFERENCE}' nor '…/{CONTROLLER_STATE}' in the bag: the reference "
                       f"recomputed from {src}" + (" and --config" if list(overrides) else ""))
    if params or not (rf or cs):
        x1d = _fill_reference(x1d, cfg, step)
    gt, gk = _gains(bag, cfg, grid)
    missed, failsafe = _missed(bag, grid)
    x = rec.x
    return RunSeries.of(np.arange(n) * step, x1d, x[:, 0], x[:, 1], x[:, 2], x[:, 3], rec.u, a1_hat=a1, a2_hat=a2,
                        name=Path(bag.path).name or str(bag.path), cfg=cfg, gains_t=gt, gains=gk, missing=missing,
                        parameters=params, missed=missed, failsafe=failsafe)


def _missed(bag: Bag, grid: "_Grid") -> tuple[np.ndarray | None, np.ndarray | None]:
    """(missed samples, fail-safe samples) from ``…/plant/missed`` if the bag
    has that topic (a realtime stack's bag: no messages, no misses), else (None, None)."""
    hits = bag.topics_named(MISSED, FLOAT64_ARRAY)
    if not hits:
        return None, None
    topic = bag.find(MISSED, FLOAT64_ARRAY)
    if not bag.messages[topic]:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows, data = _arrays(bag, topic, MISSED_COLUMNS, grid)
    return rows, rows[data[:, MISSED_COLUMNS.index("failsafe")] > 0.5]


class _Grid:
    """The recording's sample grid for the controller's arrays, whose rows lead
    with t [s]: sample i = round(t / Δt) (relative to the first state where
    the stamps are wall-clock time); off it by more than ``tolerance`` of a
    period (0.001: our bags; 0.25: a bag without our parameters) is refused."""

    def __init__(self, rec: Recording, tolerance: float):
        self.rec, self.step, self.tolerance = rec, rec.step, tolerance

    def samples(self, stamps_ns: np.ndarray, what: str) -> np.ndarray:
        """Sample index of each time [ns]; refused if off the grid or before the first sample."""
        rel = self.rec.time_ns(stamps_ns)
        x = rel / (self.step * 1e9)
        idx = np.rint(x).astype(np.int64)
        off = np.abs(x - idx) > self.tolerance
        if off.any() or (idx < 0).any():
            k = int(np.argmax(off | (idx < 0)))
            raise BagError(f"{what}: message {k} is stamped {stamps_ns[k] / 1e9:.9f} s, "
                           f"not on the sample grid of {self.step * 1e3:g} ms of the recording")
        if len(idx) and idx.max() > 100 * len(idx) + 1_000_000:
            raise BagError(f"{what}: stamps up to sample {idx.max()} for {len(idx)} messages: not one run")
        return idx


def _fitted_config(bag: Bag, cfg: Config, rec: Recording) -> Config:
    """Without stored parameters: the configuration with Δt from the stamps and
    the horizon of the recording."""
    step = rec.step
    horizon = rec.samples * step
    try:
        return build_config({"simulation.step": step, "simulation.horizon": horizon},
                            source=f"{bag.path} (Δt and horizon from the recording)", base=cfg)
    except HasControlError:                     # too short for the metric window: keep Δt only
        return build_config({"simulation.step": step}, source=f"{bag.path} (Δt from the recording)", base=cfg)


def _fill_reference(x1d: np.ndarray, cfg: Config, step: float) -> np.ndarray:
    """x1d where the controller published none (it did not answer that state):
    the run's reference, a function of its stored parameters, as the realtime
    stack scores it; so e1 = x1d − y is whole wherever the state is."""
    gaps = np.flatnonzero(np.isnan(x1d))
    if not gaps.size:
        return x1d
    rp = reference_array(cfg.reference, cfg.episode)
    out = x1d.copy()
    out[gaps] = reference_series(rp, gaps * step)[:, 0]
    return out


def _on_grid(n: int, idx: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` at samples ``idx`` of an n-sample grid (the last message of a sample wins), NaN elsewhere."""
    out = np.full(n, math.nan)
    keep = idx < n
    out[idx[keep]] = values[keep]
    return out


def _optional(bag: Bag, relative: str, msgtype: str) -> str | None:
    """The topic ``relative`` of ``msgtype`` if the bag has it with messages (two such: refused)."""
    hits = bag.topics_named(relative, msgtype)
    if len(hits) > 1:
        bag.find(relative, msgtype)             # raises, naming the topics
    return hits[0] if hits and bag.messages[hits[0]] else None


def _arrays(bag: Bag, topic: str, columns: tuple[str, ...], grid: _Grid) -> tuple[np.ndarray, np.ndarray]:
    """(sample of each message, its data) of a Float64MultiArray topic whose rows lead with t [s]."""
    data = cdr.float64_arrays([d for _, d in bag.messages[topic]], f"{bag.path}: {topic}")
    if data.shape[1] != len(columns):
        raise BagError(f"{bag.path}: {topic}: {data.shape[1]} columns, expected {len(columns)} "
                       f"({', '.join(columns)})")
    return grid.samples(np.rint(data[:, 0] * 1e9), f"{bag.path}: {topic}"), data


def _gains(bag: Bag, cfg: Config, grid: _Grid) -> tuple[np.ndarray, np.ndarray]:
    """When each gain set took effect [s] and the sets (m, 3) [1/s]: the gains
    topic, else the stored parameters' gains from t = 0, else none."""
    g = _optional(bag, GAINS, FLOAT64_ARRAY)
    if g:
        data = cdr.float64_arrays([d for _, d in bag.messages[g]], f"{bag.path}: {g}")
        if data.shape[1] != len(GAINS_COLUMNS):
            raise BagError(f"{bag.path}: {g}: {data.shape[1]} columns, expected {len(GAINS_COLUMNS)}")
        order = np.argsort(data[:, 0], kind="stable")
        return np.maximum(grid.rec.time_ns(np.rint(data[order, 0] * 1e9)) / 1e9, 0.0), data[order, 1:4]
    if PARAMETERS_KEY in bag.custom_data:
        return np.zeros(1), np.array([cfg.gains.as_tuple()])
    return np.zeros(0), np.zeros((0, 3))
