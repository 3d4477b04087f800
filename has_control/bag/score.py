"""What a run's bag says: the samples of a lock-step run, and its score (SPEC §6)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from has_control.wire import cdr
from has_control.wire.topics import COMMAND, FLOAT64_ARRAY, JOINT_STATE, REFERENCE, STATE, TRUE_STATE
from has_control.bag.base import BagError, warn
from has_control.bag.read import Bag, read_bag
from has_control.bag.samples import RunSamples
from has_control.core.cost import score_arrays


@dataclass
class RecordedRun(RunSamples):
    """A lock-step run read back from its bag, one row per sample."""

    diverged: bool
    cfg: object

    @property
    def samples(self) -> int:
        return len(self.u)


def _by_sample(stamps_ns: np.ndarray, step_ns: int, what: str, path) -> np.ndarray:
    idx = np.rint(stamps_ns / step_ns).astype(np.int64)
    grid = np.arange(len(idx))
    if len(idx) and not np.array_equal(idx, grid) and np.array_equal(np.sort(idx), grid):
        first = int(np.argmax(idx != np.arange(len(idx))))
        raise BagError(f"{path}: {what}: message {first} carries sample {idx[first]}: the samples are "
                       "reordered (log times and header stamps disagree)")
    if len(idx) and not np.array_equal(idx, np.arange(len(idx))):
        dup = len(idx) - len(np.unique(idx))
        raise BagError(f"{path}: {what} is not one message per sample from sample 0 "
                       f"({len(idx)} messages, {dup} repeated); was it a lock-step run?")
    return idx


def recorded_run(bag: Bag, overrides: Iterable[str | Path] = ()) -> RecordedRun:
    """The samples of a lock-step run in ``bag``: states, commands and reference.
    The states are the plant's true ones: ``true_state`` where the plant
    published its sensors' readings on ``state`` (``noise.added_by: plant``).
    An incomplete bag (truncated or damaged) is refused: its J would not be the run's."""
    if not bag.complete:
        raise BagError(f"{bag.path}: the bag is incomplete ({bag.damage_summary()}); "
                       "an incomplete run is not scored")
    cfg = bag.config(overrides)
    step_ns = cfg.episode.step_ns
    measured = any(t == "/" + TRUE_STATE or t.endswith("/" + TRUE_STATE) for t in bag.types)
    st = bag.find(TRUE_STATE if measured else STATE, JOINT_STATE)
    cm, rf = bag.find(COMMAND, JOINT_STATE), bag.find(REFERENCE, FLOAT64_ARRAY)
    states, commands, refs = bag.messages[st], bag.messages[cm], bag.messages[rf]
    if not states or not commands or not refs:
        empty = [t for t, m in ((st, states), (cm, commands), (rf, refs)) if not m]
        raise BagError(f"{bag.path}: no messages on {', '.join(empty)}")
    _, pos, vel, eff = cdr.joint_states([d for _, d in states], f"{bag.path}: {st}")
    _by_sample(cdr.stamps_ns([d for _, d in states]), step_ns, st, bag.path)
    _by_sample(cdr.stamps_ns([d for _, d in commands]), step_ns, cm, bag.path)
    _, u, _, _ = cdr.joint_states([d for _, d in commands], f"{bag.path}: {cm}")
    ref = cdr.float64_arrays([d for _, d in refs], f"{bag.path}: {rf}")
    _by_sample(np.rint(ref[:, 0] * 1e9).astype(np.int64), step_ns, rf, bag.path)
    m = min(len(u), len(ref), len(pos), cfg.episode.samples)
    y = pos[:, 0]
    bad = ~np.isfinite(y) | (np.abs(y) > cfg.episode.y_limit)
    diverged = bool(bad.any())
    if not diverged and m < cfg.episode.samples:
        raise BagError(f"{bag.path}: {m} of {cfg.episode.samples} samples recorded: the run is incomplete")
    return RecordedRun(ref[:m, 0], y[:m], vel[:m, 0], eff[:m, 1], eff[:m, 2], u[:m, 0],
                       ref[:m, 1], diverged, cfg)


def score_bag(path: str | Path, overrides: Iterable[str | Path] = (),
              on_warning: Callable[[str], None] = warn):
    """J, e_max, e_μ, e_σ of a recorded lock-step run (SPEC §6), as the core
    scores it; warnings (truncation, missing parameters) go to ``on_warning``."""
    bag = read_bag(path, topics=None, on_warning=on_warning)
    run = recorded_run(bag, overrides)
    return score_arrays(run["e1"], run.u, run.cfg.episode.as_array(), diverged=run.diverged), run
