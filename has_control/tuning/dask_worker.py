"""What runs on the Dask workers of :mod:`has_control.tuning.dask_evaluator`: the store of
Configs and the task functions. Imports distributed (the ``dask`` extra);
the client imports this module only when it starts a batch.
"""
from __future__ import annotations

import os
import signal
import sys
import threading

import numba
import numpy as np
from distributed import WorkerPlugin, get_worker

from has_control.core.episode import evaluate_configs
from has_control.core.params import Config


def dask_setup(worker) -> None:
    """Run by ``local:N``'s worker processes at start-up (a ``preload``):
    Ctrl-C at the terminal reaches the whole process group, but the workers
    are this command's to stop (it closes the cluster when interrupted);
    each would otherwise print its own traceback."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


class ConfigStore(WorkerPlugin):
    """The Configs of a batch on every worker, by token.

    Registered as a worker plugin, it reaches every worker once, and every
    worker that joins or restarts later when it registers with the scheduler,
    so a task carries only a Config's token. (Scattered data would not do:
    the scheduler places a task only on workers holding its dependencies,
    and its Active Memory Manager drops "superfluous" broadcast copies every
    2 s, leaving one worker with all the work and the only copy.)
    """

    def __init__(self, configs: dict[str, Config]):
        self.configs = dict(configs)


def worker_threads() -> int | None:
    """Threads of the Dask worker running the calling task (None outside one)."""
    try:
        return get_worker().state.nthreads
    except ValueError:
        return None


def stored_config(store: str, token: str) -> Config:
    """The Config of ``token`` in this worker's store named ``store``."""
    worker = get_worker()
    plugin = worker.plugins.get(store)
    if not isinstance(plugin, ConfigStore) or token not in plugin.configs:
        raise LookupError(f"worker {worker.address} has no Config {token} in store {store}")
    return plugin.configs[token]


def evaluate_chunk(gains: np.ndarray, store: str, token: str) -> np.ndarray:
    """One task: the (n, 4) scores (J, e_max, e_μ, e_σ) of ``gains`` (n, 3)
    under the stored Config ``token``, on the worker's threads."""
    cfg = stored_config(store, token)
    return np.ascontiguousarray(evaluate_configs(gains, [cfg], workers=worker_threads())[:, 0])


def warm_worker(gains: np.ndarray, cfg: Config) -> tuple[np.ndarray, dict]:
    """A worker's warm-up: load (or compile) the kernel, score the probe
    ``gains`` under ``cfg``, and say what the worker runs."""
    scores = np.ascontiguousarray(evaluate_configs(gains, [cfg], workers=worker_threads())[:, 0])
    return scores, {"pid": os.getpid(), "python": sys.version.split()[0], "numba": numba.__version__,
                    "numpy": np.__version__, "has_control": os.path.dirname(os.path.dirname(os.path.abspath(__file__)))}
