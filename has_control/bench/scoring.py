"""Scoring a recorded 10 s run from its bag."""
from __future__ import annotations

import tempfile
from pathlib import Path

from has_control.bag import PARAMETERS_KEY, BagWriter, parameters_json, score_bag, write_trace
from has_control.bench.timing import _best_of
from has_control.core.episode import simulate
from has_control.core.params import Config


def bench_scoring() -> float:
    """Seconds to score a 10 s bag (33 333 samples, 5 topics), best of 3."""

    full = Config()
    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / "ten_seconds"
        with BagWriter(bag, {PARAMETERS_KEY: parameters_json(full)}) as w:
            write_trace(w, simulate(full), full)
        score_bag(bag)                                   # warm
        return _best_of(3, lambda: score_bag(bag))
