"""The batch evaluator on a Dask cluster: :func:`~has_control.core.episode.evaluate_configs`'
contract, the work spread over Dask workers.

``with dask_batch("local:2") as batch: batch(gains, cfgs)`` returns the same
(P, S, 4) array, bit for bit, as ``evaluate_configs(gains, cfgs)``: row (p, s)
depends only on gains[p] and cfgs[s], so the split into tasks does not matter.
A spec is ``local:N`` (N worker processes of one thread on this machine,
started and stopped here) or ``tcp://host:port`` (a scheduler started with
``dask scheduler``, workers with ``dask worker``; only a client connects).

One task is (scenario s, a chunk of candidates) and runs the compiled batch
kernel on its worker's threads (:mod:`has_control.tuning.dask_worker`). Each
Config travels to each worker once per scenario set, in a worker plugin
(:class:`~has_control.tuning.dask_worker.ConfigStore`), not once per task or per
call; a task carries its Config's token. Tasks are pure and depend on no
data, so a worker that dies costs time, not results: the scheduler runs its
tasks again on the others and recomputes the results it held, and a worker
that restarts gets the store when it registers. The scheduler gives a task up
(``KilledWorker``) only after ``distributed.scheduler.allowed-failures``
(default 3) workers died while running it: a task that kills every worker it
touches stops instead of killing the cluster.

Imports no ROS; dask and distributed (the ``dask`` extra) only when a batch
is started, so :func:`parse_spec` costs nothing.
"""
from __future__ import annotations

import argparse
import asyncio
import logging
import math
import os
import re
import signal
import sys
import threading
import time
import uuid
from concurrent.futures import CancelledError
from contextlib import contextmanager
from urllib.parse import urlsplit

import numpy as np

from has_control.core.episode import LANES, evaluate_configs
from has_control.common.errors import HasControlError, shown
from has_control.core.params import Config
from has_control.config import build_config
from has_control.core.reference import check_road_memory

#: Most worker processes ``local:N`` starts (a typo such as local:1000000 would fork that many).
MAX_LOCAL_WORKERS = 1024

#: The chunk plan's cost model (:func:`plan_tasks`), measured by ``scripts/bench --dask``
#: on the reference machine (2 cores, ``local:2``; docs/scaling.md):
#: one block (LANES candidates) for one sample on one thread [s]: 7.2 ms for a 10 s episode of 33 333 samples;
BLOCK_SAMPLE_SECONDS = 2.2e-7
#: one task's cost beyond its blocks (messages, (de)serialisation, bookkeeping) [s]: 1.5 ms a trivial task;
TASK_SECONDS = 1.5e-3
#: and the part of it the scheduler (and client) spend, one task after another whatever the workers [s].
SCHEDULER_TASK_SECONDS = 5.0e-4
#: Among chunk counts whose modelled time is within this fraction of the best,
#: the plan takes the fewest that give every worker several tasks (dynamic balance).
PLAN_TOLERANCE = 0.05
#: Tasks per worker that count as "several" (a slow or shared core then costs one task, not a share).
TASKS_PER_WORKER = 4

#: The warm-up's probe: gain sets and the episode (0.2 s, metric window 0.05-0.15 s)
#: every worker evaluates once, compared bit for bit with this process.
PROBE_GAINS = np.array([[150.0, 158.0, 162.0], [656.11, 656.13, 656.14], [1200.0, 800.0, 800.0],
                        [400.0, 400.0, 400.0], [1.0e6, 1.0e6, 1.0e6]])
PROBE_PARAMETERS = {"simulation.horizon": 0.2, "metrics.skip_start": 0.05, "metrics.skip_end": 0.05}

_FORMS = "local:N (N worker processes here) or tcp://host:port (a running `dask scheduler`)"


class ClusterError(HasControlError):
    """The Dask cluster cannot be used: bad spec, no scheduler, no workers,
    workers that cannot run has_control. One line naming the culprit."""


class SpecError(ClusterError, argparse.ArgumentTypeError):
    """A malformed cluster spec; argparse shows the message as it is (``type=parse_spec``)."""


def parse_spec(text: str) -> str:
    """The normalised cluster spec (``local:N`` or ``tcp://host:port``), for
    argparse's ``type=`` as well as :func:`dask_batch`; :class:`SpecError`
    naming the spec otherwise."""
    if not isinstance(text, str):
        raise SpecError(f"dask spec {shown(text)}: expected {_FORMS}")
    spec = text.strip()
    if spec.lower().startswith("local:"):
        count = spec[len("local:"):].strip()
        if not re.fullmatch(r"[0-9]+", count):
            raise SpecError(f"dask spec {shown(text)}: local:N needs a whole number N of worker processes")
        n = int(count) if len(count.lstrip("0")) <= 6 else math.inf       # not int() of 5 000 digits
        if not 1 <= n <= MAX_LOCAL_WORKERS:
            raise SpecError(f"dask spec {shown(text)}: local:N needs 1 <= N <= {MAX_LOCAL_WORKERS} worker processes")
        return f"local:{n}"
    if "://" not in spec:
        raise SpecError(f"dask spec {shown(text)}: expected {_FORMS}")
    scheme = spec.split("://", 1)[0].lower()
    if scheme != "tcp":
        raise SpecError(f"dask spec {shown(text)}: unknown scheme {scheme!r}; expected {_FORMS}")
    try:
        parts = urlsplit(spec)
        host, port = parts.hostname, parts.port
    except ValueError:
        host = port = None
    if (not host or port is None or not 0 < port < 65536 or parts.path not in ("", "/")
            or parts.query or parts.fragment or parts.username or parts.password):
        raise SpecError(f"dask spec {shown(text)}: expected tcp://host:port with a port in 1..65535")
    return f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"


# --- the chunk plan -------------------------------------------------------------------------------

def modelled_seconds(chunks: int, scenarios: int, blocks: int, workers: int, block_seconds: float,
                     task_seconds: float = TASK_SECONDS,
                     scheduler_task_seconds: float = SCHEDULER_TASK_SECONDS) -> float:
    """Modelled wall time [s] of one call split into ``chunks`` tasks per
    scenario, for ``blocks`` blocks per scenario on ``workers`` equal workers
    (one thread each, or one unit of that many blocks: see :func:`plan_tasks`).

    Every worker runs ceil(tasks / workers) tasks of ceil(blocks / chunks)
    blocks, one after another; the scheduler handles every task in turn, so a
    call lasts at least tasks × ``scheduler_task_seconds``::

        max(ceil(S c / W) (ceil(B / c) b + o), S c o_s)
    """
    tasks = scenarios * chunks
    per_task = math.ceil(blocks / chunks) * block_seconds + task_seconds
    return max(math.ceil(tasks / workers) * per_task, tasks * scheduler_task_seconds)


def plan_tasks(candidates: int, samples: list[int], nthreads: dict[str, int] | list[int],
               block_sample_seconds: float = BLOCK_SAMPLE_SECONDS,
               chunk: int | None = None) -> list[tuple[int, int, int]]:
    """The tasks of one call: (scenario s, first, last candidate), in order.

    ``samples[s]`` is scenario s's episode length [samples]; ``nthreads`` the
    threads of each worker. A chunk is a whole number of units of T blocks of
    LANES candidates (T: the most threads of a worker), so that a worker's T
    threads each get full blocks. The chunk count per scenario minimises
    :func:`modelled_seconds`; within PLAN_TOLERANCE of the best, the fewest
    chunks that give every worker TASKS_PER_WORKER tasks win (more tasks
    balance better when cores are shared, fewer cost less overhead).
    ``chunk`` (candidates per task) overrides the plan, for measurements.
    """
    counts = list(nthreads.values()) if isinstance(nthreads, dict) else list(nthreads)
    scenarios = len(samples)
    if candidates <= 0 or scenarios == 0:
        return []
    workers = max(1, len(counts))
    unit = LANES * max(1, max(counts, default=1))                  # candidates of one unit
    units = math.ceil(candidates / unit)
    if chunk is not None:
        unit, units = int(chunk), math.ceil(candidates / int(chunk))
        chunks = units
    else:
        unit_seconds = max(samples) * block_sample_seconds         # a unit on its worker's T threads
        costs = [modelled_seconds(c, scenarios, units, workers, unit_seconds) for c in range(1, units + 1)]
        good = [c for c, cost in enumerate(costs, 1) if cost <= (1.0 + PLAN_TOLERANCE) * min(costs)]
        enough = [c for c in good if scenarios * c >= TASKS_PER_WORKER * workers]
        chunks = min(enough) if enough else max(good)
    edges = [min(candidates, round(units * i / chunks) * unit) for i in range(chunks + 1)]
    return [(s, edges[i], edges[i + 1]) for s in range(scenarios) for i in range(chunks) if edges[i] < edges[i + 1]]


# --- the client -----------------------------------------------------------------------------------

def _one_line(exc: BaseException, limit: int = 240) -> str:
    """An exception's message on one line, at most ``limit`` characters."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[:limit - 1] + "…"


def probe_scheduler(spec: str, timeout: float) -> None:
    """Ask ``spec`` (tcp://host:port) who it is, everything within ``timeout``
    seconds: connect, Dask's handshake, an ``identity`` request. Anything but
    a Dask scheduler's answer (a closed port, a web server, a listener that
    stays silent or sends garbage) is one :class:`ClusterError` line; a
    ``Client`` would wait for the handshake for ever or fail in a traceback."""
    # lazy: distributed takes about 1 s to load; only --dask needs it
    from distributed.comm import connect

    async def ask():
        comm = await connect(spec, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    async def bounded():
        return await asyncio.wait_for(ask(), timeout)
    try:
        answer = asyncio.run(bounded())
    except (asyncio.TimeoutError, TimeoutError):
        raise ClusterError(f"dask spec {spec}: no Dask scheduler answered within {timeout:g} s") from None
    except OSError as exc:                          # refused, reset, the connect timed out
        raise ClusterError(f"dask spec {spec}: no Dask scheduler there ({_one_line(exc, 120)})") from None
    except Exception:                               # garbage that msgpack reads as a 3 EiB frame, ...
        raise ClusterError(f"dask spec {spec}: not a Dask scheduler (its answer is not Dask's protocol)") from None
    if not isinstance(answer, dict) or answer.get("type") != "Scheduler":
        raise ClusterError(f"dask spec {spec}: not a Dask scheduler (it answered {shown(answer)})")


class DaskBatch:
    """A batch evaluator on a Dask cluster: ``batch(gains, cfgs)`` has the
    contract of :func:`~has_control.core.episode.evaluate_configs`.

    Starting one connects (or starts ``local:N``), waits up to
    ``worker_timeout`` seconds for ``min_workers`` workers (``local:N``: N),
    and warms every worker: it loads has_control and the compiled kernel
    (numba's cache, or a compile of a few seconds) and checks that the
    worker computes the same bits as this process (same has_control, numba,
    NumPy, libm), so the first call's time is the work's. A worker that joins
    later loads the kernel in its first task. Use as a context manager, or
    call :meth:`close`.
    """

    def __init__(self, spec: str, connect_timeout: float = 5.0, worker_timeout: float = 60.0,
                 min_workers: int = 1, check_bits: bool = True, chunk: int | None = None):
        self.spec = parse_spec(spec)
        self.chunk = chunk                    # candidates per task; None: plan_tasks decides
        self.min_workers = int(self.spec.split(":")[1]) if self.spec.startswith("local:") else max(1, int(min_workers))
        self.connect_timeout = float(connect_timeout)
        self.worker_timeout = float(worker_timeout)
        self.client = None
        self.cluster = None
        self._store_name = f"has-control-configs-{uuid.uuid4().hex[:16]}"     # this batch's, on a shared cluster
        self._tokens: dict[Config, str] | None = None     # the registered store's Configs
        self._signals = _Signals()
        self._output = None
        try:
            self._signals.install()
            self._start()
            self._signals.check()
            self._warm(check_bits)
            self._signals.check()
        except BaseException:
            self.close()
            raise

    def _start(self) -> None:
        if not self.spec.startswith("local:"):
            return self._connect()
        # the workers' standard error passes through this process (_WorkerOutput): a Ctrl-C at the terminal
        # reaches the whole process group, so a worker half-way through its imports prints a traceback of
        # its own; after a signal their output is dropped, otherwise passed on
        self._output = _WorkerOutput(self._signals)
        with self._output.inherited():
            self._connect()

    def _connect(self) -> None:
        try:
            from distributed import Client, LocalCluster

            from has_control.tuning import dask_worker  # noqa: F401  (the workers' side needs distributed too)
        except ImportError as exc:
            raise ClusterError(f"dask spec {self.spec}: needs dask and distributed "
                               f"(pip install 'has_control[dask]'): {exc}") from None
        if self.spec.startswith("local:"):
            # the scheduler's HTTP server (always started) on a free port, never Dask's 8787: another program
            # holding that port would cost a three-line warning; the resource tracker's notice of the workers'
            # semaphores at exit (printed by its own process after a Ctrl-C) is not this command's to show
            if "ignore:resource_tracker:UserWarning" not in sys.warnoptions:
                sys.warnoptions.append("ignore:resource_tracker:UserWarning")
            http = {"dashboard": False, "dashboard_address": "127.0.0.1:0"}
            self.cluster = LocalCluster(n_workers=self.min_workers, threads_per_worker=1, processes=True,
                                        host="127.0.0.1", dashboard_address=None, scheduler_kwargs=http,
                                        # the workers' warnings (a task cancelled by a Ctrl-C's close) stay in
                                        # them; their errors still show
                                        silence_logs=logging.ERROR,
                                        preload=[dask_worker.__name__])      # its dask_setup: Ctrl-C is ours
            self.client = Client(self.cluster, set_as_default=False)
        else:
            probe_scheduler(self.spec, self.connect_timeout)
            try:
                self.client = Client(self.spec, timeout=self.connect_timeout, set_as_default=False)
            except (OSError, TimeoutError) as exc:
                raise ClusterError(f"dask spec {self.spec}: no Dask scheduler answered within "
                                   f"{self.connect_timeout:g} s ({exc})") from None
        self._workers(self.min_workers)

    def _workers(self, least: int = 1) -> dict[str, int]:
        """Threads of each worker now; waits up to ``worker_timeout`` for ``least`` workers."""
        nthreads = self.client.nthreads()
        if len(nthreads) < least:
            try:
                self.client.wait_for_workers(least, timeout=self.worker_timeout)
            except (OSError, TimeoutError):
                raise ClusterError(f"dask spec {self.spec}: the scheduler has {len(self.client.nthreads())} of "
                                   f"{least} workers after {self.worker_timeout:g} s "
                                   f"(start them: dask worker {self.spec})") from None
            nthreads = self.client.nthreads()
        return nthreads

    def _warm(self, check_bits: bool) -> None:
        # lazy: dask_worker imports distributed (the optional "dask" extra), loaded only once a cluster is used
        from has_control.tuning.dask_worker import warm_worker
        cfg = build_config(PROBE_PARAMETERS, source="dask warm-up", base=Config())
        workers = sorted(self._workers(self.min_workers))
        futures = [self.client.submit(warm_worker, PROBE_GAINS, cfg, workers=[w], allow_other_workers=False,
                                      pure=False) for w in workers]
        expected = evaluate_configs(PROBE_GAINS, [cfg], workers=1)[:, 0] if check_bits else None
        self._signals.check()                  # a Ctrl-C noted while the kernels loaded
        for worker, future in zip(workers, futures):
            try:
                scores, info = future.result(timeout=self.worker_timeout + 120.0)
            except Exception as exc:
                if "deserialization of the task graph" in str(exc):
                    raise ClusterError(f"dask spec {self.spec}: the scheduler cannot load has_control's tasks "
                                       f"(its host needs the same has_control as the workers): "
                                       f"{_one_line(exc.__cause__ or exc)}") from None
                raise ClusterError(f"dask spec {self.spec}: worker {worker} cannot run has_control: "
                                   f"{type(exc).__name__}: {_one_line(exc)}") from None
            if check_bits and not np.array_equal(scores, expected, equal_nan=True):
                raise ClusterError(f"dask spec {self.spec}: worker {worker} computes other bits than this process "
                                   f"(has_control {info['has_control']}, numba {info['numba']}, NumPy "
                                   f"{info['numpy']}, Python {info['python']}): install the same everywhere")

    def _stored(self, cfgs: list[Config]) -> list[str]:
        """The tokens of ``cfgs`` in this batch's ConfigStore: registers the
        store anew (on every worker, now and later, replacing the last) when
        a Config is not in it; it then holds this call's Configs only."""
        # lazy: dask and distributed are the optional "dask" extra, loaded only once a cluster is used
        from dask.base import tokenize
        from has_control.tuning.dask_worker import ConfigStore
        if self._tokens is None or any(c not in self._tokens for c in cfgs):
            tokens = {c: tokenize(c) for c in dict.fromkeys(cfgs)}
            self._tokens = None
            self.client.register_plugin(ConfigStore({t: c for c, t in tokens.items()}), name=self._store_name)
            self._tokens = tokens
        return [self._tokens[c] for c in cfgs]

    def __call__(self, gains, cfgs) -> np.ndarray:
        """(P, S, 4) scores (J, e_max, e_μ, e_σ) of every gain set (P, 3) under
        every Config; +inf when diverged. Same bits as ``evaluate_configs``."""
        # lazy: dask_worker imports distributed (the optional "dask" extra)
        from has_control.tuning.dask_worker import evaluate_chunk
        if self.client is None:
            raise ClusterError(f"dask spec {self.spec}: the batch is closed")
        if self.client.status in ("closing", "closed"):       # it gave up reconnecting to a lost scheduler
            raise ClusterError(f"dask spec {self.spec}: lost the cluster (the client has closed)")
        k = np.ascontiguousarray(np.atleast_2d(np.asarray(gains, dtype=np.float64)))
        if k.ndim != 2 or k.shape[1] != 3:
            raise ValueError(f"gains: expected shape (P, 3), got {np.shape(gains)}")
        cfgs = list(cfgs)
        check_road_memory([(c.reference, c.episode) for c in cfgs])     # each worker would build them all
        out = np.empty((k.shape[0], len(cfgs), 4))
        if out.size == 0:
            return out
        from distributed import KilledWorker             # lazy: distributed is the optional "dask" extra
        try:
            tasks = plan_tasks(k.shape[0], [c.episode.samples for c in cfgs], self._workers(), chunk=self.chunk)
            tokens = self._stored(cfgs)
            futures = self.client.map(evaluate_chunk, [k[lo:hi] for _, lo, hi in tasks],
                                      [self._store_name] * len(tasks), [tokens[s] for s, _, _ in tasks], pure=True)
            self._wait(futures)
            parts = self.client.gather(futures)
        except KilledWorker as exc:
            raise ClusterError(f"dask spec {self.spec}: {exc.allowed_failures + 1} workers died running task "
                               f"{exc.task} (distributed.scheduler.allowed-failures = {exc.allowed_failures}); "
                               f"the last was {exc.last_worker.address}: see its log") from None
        except (OSError, CancelledError) as exc:             # OSError: CommClosedError, TimeoutError
            raise ClusterError(f"dask spec {self.spec}: lost the cluster ({type(exc).__name__}: "
                               f"{_one_line(exc)})") from None
        except KeyboardInterrupt:                            # Ctrl-C, SIGTERM: see _quiet
            _quiet()
            raise
        for (s, lo, hi), part in zip(tasks, parts):
            out[lo:hi, s] = part
        return out

    def _wait(self, futures) -> None:
        """Until ``futures`` are done (or one failed: gather says which), a signal seen
        within 0.1 s even if its KeyboardInterrupt was swallowed (raised inside a gc
        callback of distributed's, it is only "ignored" and the work would run to its end)."""
        pending = list(futures)
        while pending:
            self._signals.check()
            pending = [f for f in pending if not f.done()]
            if any(f.status == "error" for f in futures if f.done()):
                break
            if pending:
                time.sleep(0.1)
        self._signals.check()

    def __exit__(self, kind, *exc) -> None:
        if kind is not None and issubclass(kind, KeyboardInterrupt):
            _quiet()
        self.close()

    def close(self) -> None:
        """Remove the Config store, disconnect, and stop ``local:N``'s processes."""
        client, cluster, stored = self.client, self.cluster, self._tokens
        self.client = self.cluster = self._tokens = None
        self._signals.restore()
        try:
            if client is not None and stored is not None and cluster is None:
                client.unregister_worker_plugin(self._store_name)  # a shared scheduler keeps plugins
        except Exception:                                         # the scheduler may be gone: nothing to tidy
            pass
        finally:
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()

    def __enter__(self) -> "DaskBatch":
        return self


class _Signals:
    """While a batch is open: Ctrl-C and SIGTERM are noted as well as raised
    (KeyboardInterrupt), so that :meth:`check` raises again where one raised
    inside a callback of distributed's was swallowed. Main thread only; the
    previous handlers are back at :meth:`restore`."""

    def __init__(self):
        self.seen: list[int] = []
        self._previous: dict = {}

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous = signal.getsignal(sig)
            if previous in (signal.SIG_IGN, None):
                continue
            self._previous[sig] = previous
            signal.signal(sig, self._note)

    def _note(self, signum, frame) -> None:
        self.seen.append(signum)
        if not _in_callback(frame):
            raise KeyboardInterrupt                # else at the next check(), outside the callback

    def check(self) -> None:
        if self.seen:
            raise KeyboardInterrupt

    def restore(self) -> None:
        if threading.current_thread() is threading.main_thread():
            for sig, handler in self._previous.items():
                signal.signal(sig, handler)
        self._previous.clear()


#: Code that calls Python back from C or from the collector, where a KeyboardInterrupt would only be
#: "ignored" with a traceback (numba's compile cache via llvmlite's ctypes callback, distributed's gc hook).
_CALLBACK_SITES = ("/llvmlite/", "/numba/", "/distributed/gc.py", "/ctypes/")


def _in_callback(frame) -> bool:
    while frame is not None:
        if any(site in frame.f_code.co_filename for site in _CALLBACK_SITES):
            return True
        frame = frame.f_back
    return False


class _WorkerOutput:
    """File descriptor 2 of the processes a ``local:N`` cluster starts: a pipe
    whose lines this process passes on to its own standard error, each after
    :data:`HOLD` s, unless a signal came meanwhile (then nothing more)."""

    HOLD = 0.3                                   # [s] a worker's traceback comes within this of the signal

    def __init__(self, signals: "_Signals"):
        self.signals = signals
        self._read, self._write = os.pipe()
        self._out = os.dup(2)
        threading.Thread(target=self._pass_on, name="has-control-worker-stderr", daemon=True).start()

    @contextmanager
    def inherited(self):
        """While the block runs, this process's fd 2 is the pipe (what it starts inherits it)."""
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(self._write, 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            os.close(self._write)                # the workers hold theirs: EOF when the last one ends

    def _pass_on(self) -> None:
        with os.fdopen(self._read, "rb", buffering=0) as pipe:
            while True:
                data = pipe.read(65536)
                if not data:
                    break
                time.sleep(self.HOLD)
                if self.signals.seen:
                    continue                     # an interrupted command ends in one line: drain, drop
                try:
                    os.write(self._out, data)
                except OSError:
                    pass
        os.close(self._out)


def _quiet() -> None:
    """After Ctrl-C or SIGTERM the command ends in one line, "interrupted":
    closing the client cancels its gathers, and each cancelled one would log
    "Task exception was never retrieved ... AllExit" with a traceback (885 of
    them for one robustness table), and the cluster's shutdown its own
    warnings. Nothing they say matters to an interrupted command."""
    for name in ("asyncio", "distributed", "tornado"):
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


def dask_batch(spec: str, **options) -> DaskBatch:
    """A started :class:`DaskBatch` for ``spec`` (``local:N`` or ``tcp://host:port``);
    ``with dask_batch(spec) as batch: tune(cfg, tuning, batch=batch)``."""
    return DaskBatch(spec, **options)


__all__ = ["ClusterError", "SpecError", "DaskBatch", "dask_batch", "parse_spec", "plan_tasks", "modelled_seconds"]
