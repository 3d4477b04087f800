"""The tuner's lanes as a batch evaluator (ROS-free: a lane is any object with ``run``).

:class:`GraphEvaluator` makes the lanes (:class:`~has_control.nodes.lanes.Lane`:
one plant/controller pair driven through its services) a batch evaluator with
the contract of :func:`~has_control.core.episode.evaluate_configs` (as
:class:`~has_control.tuning.dask_evaluator.DaskBatch` does for a Dask
cluster): ``evaluator(gains, [cfg])`` runs every candidate through a free lane
and returns the (P, 1, 4) array of (J, e_max, e_μ, e_σ), +inf where an episode
could not be scored. The tuner node hands it to the session as ``batch``.
"""
from __future__ import annotations

import math
import queue
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from has_control.common.errors import HasControlError

#: What an episode that could not be scored gives: J, e_max, e_μ, e_σ all +inf.
UNSCORED = (math.inf, math.inf, math.inf, math.inf)


class EpisodeLane(Protocol):
    """What the evaluator asks of a lane: one episode with ``gains`` recorded to ``bag``,
    its (J, e_max, e_μ, e_σ) (:data:`UNSCORED` when it cannot be scored)."""

    def run(self, gains, cfg, bag: Path, timeout: float) -> tuple: ...


class GraphEvaluator:
    """The lanes as a batch evaluator (see the module docstring). Episode bags go
    under ``episodes`` as ``batchNNNN_candidateNNN`` (deleted once scored unless
    ``keep``); ``check()`` runs before each episode (e.g. raises on a cancel);
    ``announce(cfg)`` is called once, before the first episode."""

    def __init__(self, lanes: list[EpisodeLane], episodes: Path, timeout: float, keep: bool = False,
                 check: Callable[[], None] = lambda: None, announce: Callable | None = None):
        self.lanes, self.episodes, self.timeout, self.keep = lanes, Path(episodes), timeout, keep
        self.check, self.announce = check, announce
        self.batches = 0                           # calls so far (names the bags)
        self._free: queue.Queue[EpisodeLane] = queue.Queue()
        for lane in lanes:
            self._free.put(lane)
        self._pool = ThreadPoolExecutor(max_workers=len(lanes), thread_name_prefix="tuner-lane")

    def __call__(self, gains, cfgs) -> np.ndarray:
        if len(cfgs) != 1:
            raise HasControlError(f"graph evaluator: the lanes run one configuration, not {len(cfgs)} "
                                  "(scenarios need the batch evaluator)")
        cfg = cfgs[0]
        if self.announce is not None:
            self.announce(cfg)
            self.announce = None
        k = np.asarray(gains, dtype=np.float64).reshape(-1, 3)
        rows = list(self._pool.map(lambda job: self._one(cfg, *job), enumerate(k)))
        self.batches += 1
        return np.array(rows, dtype=np.float64).reshape(len(k), 1, 4)

    def _one(self, cfg, i: int, gains) -> tuple:
        self.check()
        lane = self._free.get()
        try:
            bag = self.episodes / f"batch{self.batches:04d}_candidate{i:03d}"
            row = lane.run(gains, cfg, bag, self.timeout)
            if not self.keep:
                shutil.rmtree(bag, ignore_errors=True)
            return row
        finally:
            self._free.put(lane)

    def close(self) -> None:
        self._pool.shutdown(wait=False)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
