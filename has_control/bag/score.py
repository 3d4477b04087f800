"""What a run's bag says: the samples of a lock-step run, and its score (SPEC §6)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from has_control.wire import cdr
from has_control.wire.topics import COMMAND, FLOAT64_ARRAY, JOINT_STATE, REFERENCE, TRUE_STATE
from has_control.bag.base import PARAMETERS_KEY, BagError, warn
from has_control.bag.read import Bag
from has_control.bag.recorded import Reading, has_topic, on_grid, read_recording, read_run_bag
from has_control.core.episode import EpisodeArrays
from has_control.core.reference import reference_series
from has_control.core.run import Run
from has_control.core.cost import score_arrays


@dataclass(frozen=True)
class RecordedRun(Run):
    """A lock-step run read back from its bag, one row per sample (the
    controller's columns NaN: a score needs state, command and reference)."""

    diverged: bool
    cfg: object

    @property
    def samples(self) -> int:
        return len(self.data)


def recorded_run(bag: Bag, overrides: Iterable[str | Path] = (), reading: Reading = Reading()) -> RecordedRun:
    """The samples of a lock-step run in ``bag``: states, commands and reference.
    The states are the plant's true ones: ``true_state`` where the plant
    published its sensors' readings on ``state`` (``noise.added_by: plant``).
    States and commands are read by :func:`~has_control.bag.recorded.read_recording`
    (either layout, any epoch, jitter within its tolerance, repeats collapsed).
    The reference is ``…/controller/reference``, else recomputed from the
    configuration (said in one line). Dropped states, and states read as not
    measured (non-finite or impossible values), in runs of at most
    MAX_INTERPOLATED samples are interpolated from their neighbours (said in
    one line); non-finite states to the end of the recording are the run
    diverging (J = inf, said). A ``noise.added_by: plant`` bag without
    ``true_state`` scores the readings, said in one line. Refused, one line: an incomplete bag (truncated or damaged), a
    longer gap or a sample without its command (the J of what is left would
    not be the run's), fewer samples than the
    configuration's horizon unless the run diverged."""
    if not bag.complete:
        raise BagError(f"{bag.path}: the bag is incomplete ({bag.damage_summary()}); "
                       "an incomplete run is not scored")
    cfg = bag.config(overrides)
    rec = read_recording(bag, cfg.episode.step, reading, true_state=True, emit=False)
    if rec.command_topic is None or not rec.command.any():
        raise BagError(f"{bag.path}: no messages on a command topic ('…/{COMMAND}' {JOINT_STATE}, or the "
                       f"ros2_control layout's {FLOAT64_ARRAY} commands); topics: {', '.join(sorted(bag.types))}")
    n = min(rec.samples, cfg.episode.samples, _through(rec.command))
    x = rec.x.copy()
    finite = np.isfinite(x).all(axis=1)
    state = rec.state & finite
    # a state read as not measured (non-finite or impossible, counted in rec.notes) inside the run is a
    # dropped sample; from one on to the end, the run diverged there (J = inf, said below)
    tail = _through(state[:n])
    bad_tail = int((rec.state[tail:n] & ~finite[tail:n]).sum())
    if bad_tail:
        n = tail + 1
        x[tail] = math.inf
        state[tail] = True
    filled = _interpolated(state[:n], x[:n])
    for what, have in (("state", state if not filled else np.ones_like(state)), ("command", rec.command)):
        lack = np.flatnonzero(~have[:n])
        if len(lack):
            topic = rec.state_topic if what == "state" else rec.command_topic
            raise BagError(f"{bag.path}: {topic} is not one message per sample from sample 0 ({len(lack)} of {n} "
                           f"samples have no {what}, the first at t = {lack[0] * rec.step:.6f} s): a run with "
                           "dropped samples is not scored (its J would not be the run's); plot shows it")
    for line in rec.notes:
        bag.on_warning(line)
    if filled:
        bag.on_warning(f"{bag.path}: {filled} of {n} samples without a state: each interpolated from its "
                       f"neighbours (gaps of at most {MAX_INTERPOLATED} samples) to score the run (dropped, or "
                       "read as not measured)")
    if bad_tail:
        bag.on_warning(f"{bag.path}: {rec.state_topic}: the states from t = {tail * rec.step:.6f} s to the end are "
                       "not finite: the run is scored as diverged there (J = inf)")
    if getattr(cfg.noise, "added_by", "") == "plant" and not rec.state_topic.endswith(TRUE_STATE):
        bag.on_warning(f"{bag.path}: noise.added_by is plant and the bag has no '…/{TRUE_STATE}': the states on "
                       f"{rec.state_topic} are scored as recorded (from the node graph: the sensors' readings, "
                       "not the plant's true states)")
    step = cfg.episode.step
    if has_topic(bag, REFERENCE, FLOAT64_ARRAY):
        rf = bag.find(REFERENCE, FLOAT64_ARRAY)
        if not bag.messages[rf]:
            raise BagError(f"{bag.path}: no messages on {rf}")
        ref = cdr.float64_arrays([d for _, d in bag.messages[rf]], f"{bag.path}: {rf}")
        rows, _ = on_grid(rec.time_ns(np.rint(ref[:, 0] * 1e9)), 0, step * 1e9, f"{bag.path}: {rf}")
        x1d = np.full(rec.samples, np.nan)
        keep = rows < rec.samples
        x1d[rows[keep]] = ref[keep, 1]
        n = min(n, _through(~np.isnan(x1d)))
        lack = np.flatnonzero(np.isnan(x1d[:n]))
        if len(lack):
            raise BagError(f"{bag.path}: {rf} is not one message per sample from sample 0 ({len(lack)} of {n} "
                           f"samples have none, the first at t = {lack[0] * step:.6f} s)")
    else:
        rp = EpisodeArrays.from_config(cfg).reference
        x1d = reference_series(rp, np.arange(n) * step)[:, 0]
        src = f"{PARAMETERS_KEY} of the bag" if PARAMETERS_KEY in bag.custom_data else "the configuration files"
        bag.on_warning(f"{bag.path}: no '…/{REFERENCE}' in the bag: the reference and the metrics recomputed "
                       f"from {src}" + (" and --config" if list(overrides) else ""))
    y = x[:n, 0]
    bad = ~np.isfinite(y) | (np.abs(y) > cfg.episode.y_limit)
    diverged = bool(bad.any())
    if not diverged and n < cfg.episode.samples:
        raise BagError(f"{bag.path}: {n} of {cfg.episode.samples} samples recorded: the run is incomplete")
    return RecordedRun.of(np.arange(n) * step, x1d[:n], y, x[:n, 1], x[:n, 2], x[:n, 3], rec.u[:n],
                          diverged=diverged, cfg=cfg)


#: The longest run of dropped states a score interpolates over [samples] (0.9 ms at the reference step).
MAX_INTERPOLATED = 3


def _interpolated(have: np.ndarray, x: np.ndarray) -> int:
    """Fill, in place, the rows of ``x`` whose state is missing (``~have``) by
    linear interpolation between their neighbours, when every missing run is
    at most MAX_INTERPOLATED samples long and inside the record; returns how
    many (0: nothing filled, the caller refuses a dropped sample as before)."""
    lack = np.flatnonzero(~have)
    if len(lack) == 0 or lack[0] == 0 or lack[-1] == len(have) - 1:
        return 0
    runs = np.split(lack, np.flatnonzero(np.diff(lack) > 1) + 1)
    if max(len(r) for r in runs) > MAX_INTERPOLATED:
        return 0
    idx = np.arange(len(have))
    for c in range(x.shape[1]):
        x[lack, c] = np.interp(lack, idx[have], x[have, c])
    return int(len(lack))


def _through(have: np.ndarray) -> int:
    """Samples up to the last one ``have`` holds (a run that ends early, e.g. diverged, stops there)."""
    return int(np.flatnonzero(have)[-1]) + 1 if have.any() else 0


def score_bag(path: str | Path, overrides: Iterable[str | Path] = (),
              on_warning: Callable[[str], None] = warn, reading: Reading = Reading()):
    """J, e_max, e_μ, e_σ of a recorded lock-step run (SPEC §6), as the core
    scores it; warnings (truncation, missing parameters) go to ``on_warning``."""
    bag = read_run_bag(path, on_warning=on_warning)
    run = recorded_run(bag, overrides, reading)
    return score_arrays(run["e1"], run.u, run.cfg.episode.as_array(), diverged=run.diverged), run
