"""Tuning sessions recorded to a bag, and resumed from it after a crash.

A session bag (``DIR/session``, rosbag2 MCAP) holds, as std_msgs/String JSON:

* ``/tuner/settings``: the tuning settings and every model parameter, first;
* ``/tuner/iteration``: per iteration (one batch of candidates), every
  candidate's position and cost, the best so far and the batch's mean and
  spread (an :class:`IterationRecord`);
* ``/tuner/swarm``: per iteration, the optimiser's state needed to resume (a
  swarm: positions, velocities, personal bests, the random generator's state;
  ``cma-restarts``: its settings and seed, resumed by replaying the costs of
  the iteration records);
* ``/tuner/result``: the final result (the keys of ``tune --json``, with the
  bound diagnostics);

and the validation run of the best gains under ``/validation/...``, the same
topics a recorded run has, so ``has-control score DIR/session`` scores it.

After each iteration the bag's chunk is closed and flushed, so killing the
tuner at any moment loses at most the iteration in progress.
:func:`resume` reads what survived (a truncated bag included) and returns the
swarm as it was after the last complete iteration; continuing it gives
exactly the result of an uninterrupted run.
"""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from has_control.bag.read import parameters_from_json
from has_control.common.errors import HasControlError, shown
from has_control.common.json_bounded import loads_bounded
from has_control.tuning.bounds import BoundDiagnostics
from has_control.tuning.methods import new_optimiser, restore as restore_optimiser
from has_control.tuning.restarts import Restarts
from has_control.bag import (
    BagError, BagWriter, PARAMETERS_KEY, QosSpec, STRING, parameters_json, read_bag, typestore, warn, write_trace,
)
from has_control.common.files import DirectoryLock, write_atomic
from has_control.config import build_config, write_gains_params
from has_control.core.episode import simulate
from has_control.tuning.optimiser import OptimiseResult, record_dict, record_from
from has_control.tuning.swarm import Swarm
from has_control.tuning.tuner import TuneResult, Tuning, tune, tuning_from_json, tuning_json

SESSION = "session"
SETTINGS, ITERATION, SWARM, RESULT = "/tuner/settings", "/tuner/iteration", "/tuner/swarm", "/tuner/result"
LANES = "/tuner/lanes"              # the tuner node's lanes' parameters as read back before the validation
VALIDATION = "/validation"
TUNING_KEY = "has_control/tuning"
LOCK = ".lock"                      # DIR/.lock: flock'ed by the one process writing the session
RESULT_FILE = "tune.json"           # written last: its presence says the session is finished


def _string(text: str) -> bytes:
    msg = typestore().types[STRING](data=text)
    return bytes(typestore().serialize_cdr(msg, STRING))


def _unstring(data: bytes) -> str:
    n = int.from_bytes(data[4:8], "little")
    return data[8:8 + n - 1].decode()


def _json(data: bytes) -> dict | None:
    """The JSON object a std_msgs/String message carries (nesting bounded),
    None if it is damaged or anything else."""
    try:
        doc = loads_bounded(_unstring(data), "record")
    except (HasControlError, UnicodeDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


class Session:
    """Writes one tuning session's bag (see the module's docstring)."""

    def __init__(self, directory: str | Path, tuning: Tuning, cfg, evaluator: str = "batch",
                 _copy_from=None, _lock: DirectoryLock | None = None, replace: bool = False):
        self.directory = Path(directory)
        self.path = self.directory / SESSION
        self.lock = _lock or DirectoryLock(self.directory, LOCK, "the tuning session")
        if _copy_from is None:
            self._clear(replace)
        settings = {"tuning": tuning_json(tuning), "evaluator": evaluator,
                    "parameters": json.loads(parameters_json(cfg))}
        self.writer = BagWriter(self.path, {PARAMETERS_KEY: parameters_json(cfg),
                                            TUNING_KEY: json.dumps(settings["tuning"])})
        for topic in (SETTINGS, ITERATION, SWARM, RESULT):
            self.writer.add_topic(topic, STRING, QosSpec(depth=10, transient_local=topic == SETTINGS))
        if _copy_from is None:
            self.writer.write(SETTINGS, time.time_ns(), _string(json.dumps(settings)))
        else:
            for topic, t, data in _copy_from:
                self.writer.write(topic, t, data)
        self.writer.sync()

    def _clear(self, replace: bool) -> None:
        """Refuse an existing session or result here, or (``replace``) remove them."""
        old = existing(self.directory)
        if old and not replace:
            self.lock.release()
            raise HasControlError(f"{old[0]}: exists already; --force to overwrite")
        for p in old:
            shutil.rmtree(p) if p.is_dir() else p.unlink()

    def release(self) -> None:
        """Let another process write this session (also when this one ends)."""
        self.lock.release()

    def record(self, swarm) -> None:
        """After an iteration: its record and the swarm's state, then flush."""
        now = time.time_ns()
        self.writer.write(ITERATION, now, _string(json.dumps(record_dict(swarm.history[-1]))))
        self.writer.write(SWARM, now, _string(json.dumps(swarm.state_dict(history=False))))
        self.writer.sync()

    def finish(self, result: dict, validation_trace=None, cfg=None) -> Path:
        """The result, the validation run of the best gains, and close the bag."""
        self.writer.write(RESULT, time.time_ns(), _string(json.dumps(result)))
        if validation_trace is not None:
            write_trace(self.writer, validation_trace, cfg, VALIDATION, log_offset_ns=time.time_ns())
        return self.writer.close()

    def close(self) -> Path:
        return self.writer.close()


def existing(directory: str | Path) -> list[Path]:
    """What a new session in ``directory`` would replace: its session bag, result, interrupted bag."""
    d = Path(directory)
    return [p for p in (d / SESSION, d / RESULT_FILE, d / (SESSION + ".interrupted")) if p.exists()]


def conflict(record: str | Path | None, resume_dir: str | Path | None, force: bool = False) -> str | None:
    """Why a session recorded in ``record`` (or resuming ``resume_dir``) cannot start, known
    before it runs (a front end answers it at once): a session already there without
    ``force``, another process writing it, nothing to resume; None when it can."""
    if resume_dir:
        d = Path(resume_dir)
        if not (d / SESSION).exists() and not (d / (SESSION + ".interrupted")).exists():
            return f"{d / SESSION}: no session bag to resume"
        if (d / RESULT_FILE).exists():
            return f"{d / SESSION}: the session has finished already (see {d / RESULT_FILE})"
        return _locked(d)
    if not record:
        return None
    d = Path(record)
    if d.exists() and not d.is_dir():
        return f"{d}: not a directory"
    old = existing(d) if d.is_dir() else []
    if old and not force:
        return f"{old[0]}: exists already; force:=true (--force) to overwrite"
    return _locked(d) if d.is_dir() else None


def _locked(d: Path) -> str | None:
    """Why ``d``'s session lock cannot be taken now (another process writes the session), or None."""
    try:
        DirectoryLock(d, LOCK, "the tuning session").release()
    except HasControlError as exc:
        return str(exc)
    return None


def write_lanes(writer, lanes: list[dict]) -> None:
    """The lanes' parameters as read back (one JSON message ``{"lanes": [{"lane", "controller",
    "plant"}]}`` on ``/tuner/lanes``) into an open session bag."""
    writer.add_topic(LANES, STRING, QosSpec(depth=10))
    writer.write(LANES, time.time_ns(), _string(json.dumps({"lanes": lanes}, default=_plain_json)))


def _plain_json(value):
    return value.tolist() if hasattr(value, "tolist") else str(value)


def rewrite_result(directory: str | Path, out: dict) -> None:
    """``tune.json`` again with ``out`` (a front end's keys added after the session, e.g. its validation)."""
    write_atomic(Path(directory) / RESULT_FILE, json.dumps(out, indent=1) + "\n")


@dataclasses.dataclass
class Resumed:
    swarm: object                       # the optimiser, as after the last good iteration
    tuning: Tuning
    cfg: object
    evaluator: str
    session: Session
    result: dict | None = None          # the stored result of a session whose final writes were cut short


def resume(directory: str | Path, on_warning=warn) -> Resumed:
    """The session in ``directory`` at its last good iteration, writing on.

    The directory is locked first (a second resume is refused). The surviving
    bag is moved to ``session.interrupted``, its good iterations are copied
    into a fresh ``session`` bag (flushed), and only then is the old one
    deleted: a crash during resume loses nothing. Iterations are good up to
    the first one whose record or swarm state is missing, damaged or
    inconsistent (a corrupted chunk is skipped by the reader); the session
    resumes from the one before, with a warning, which gives the same
    result. A session whose result is stored but whose ``tune.json`` is not
    (the final writes were interrupted) comes back with ``result`` set.
    """
    d = Path(directory)
    old = d / (SESSION + ".interrupted")
    cur = d / SESSION
    if not (old.exists() or cur.exists()):
        raise BagError(f"{cur}: no session bag to resume (was the session started with --out {d}?)")
    lock = DirectoryLock(d, LOCK, "the tuning session")
    if old.exists():                      # an earlier resume was interrupted: start from its source
        if cur.exists():
            shutil.rmtree(cur)
    elif cur.exists():
        cur.rename(old)
    bag = read_bag(old, topics=(SETTINGS, ITERATION, SWARM, RESULT), on_warning=on_warning)
    results = [r for r in (_json(x) for _, x in bag.messages.get(RESULT) or []) if _result_ok(r)]
    if results and (d / RESULT_FILE).exists():
        old.rename(cur)
        lock.release()
        raise BagError(f"{cur}: the session has finished already (see {d / RESULT_FILE})")
    try:
        restored = restore(bag.messages, old)
    except HasControlError:
        lock.release()
        raise
    tuning, cfg, evaluator, k, swarm = restored
    settings = bag.messages.get(SETTINGS) or []
    states = bag.messages.get(SWARM) or []
    records = bag.messages.get(ITERATION) or []
    if k < max(len(records), len(states)) or not bag.complete:
        on_warning(f"{old}: records damaged or missing after iteration {k}: resuming from iteration {k}, "
                   "the last good one")
    if swarm is None:
        swarm = new_optimiser(tuning.method, tuning.bounds, tuning.swarm, tuning.restarts, tuning.seed)
    keep = [(SETTINGS, *settings[0])]
    keep += [(ITERATION, *r) for r in records[:k]] + [(SWARM, *x) for x in states[:k]]
    keep.sort(key=lambda m: m[1])
    session = Session(d, tuning, cfg, evaluator, _copy_from=keep, _lock=lock)
    shutil.rmtree(old)
    return Resumed(swarm, tuning, cfg, evaluator, session, results[-1] if results and swarm.done else None)


def restore(messages: dict, where) -> tuple[Tuning, object, str, int, Swarm | None]:
    """What a session's messages (topic: [(time, bytes)]) say, every record
    checked: (tuning, cfg, evaluator, k, the swarm after its last good
    iteration k, None for 0). The settings pass the command line's checks
    (a session edited by hand resumes only if ``tune`` would start it) or
    are one line naming ``where``; a damaged or inconsistent iteration ends
    the good ones (:func:`_last_good_iteration`)."""
    settings = messages.get(SETTINGS) or []
    s = _json(settings[0][1]) if settings else None
    if s is None or not isinstance(s.get("tuning"), dict):
        raise BagError(f"{where}: no readable {SETTINGS} message; cannot resume")
    where = f"{where} ({SETTINGS})"
    try:
        if not isinstance(s.get("parameters"), dict):
            raise BagError(f"{where}: parameters = {shown(s.get('parameters'))}: expected an object of "
                           "parameter names to values")
        if s.get("evaluator", "batch") not in EVALUATORS:
            raise BagError(f"{where}: evaluator = {shown(s.get('evaluator'))}: expected one of "
                           f"{', '.join(EVALUATORS)}")
        # the checks the command line's settings pass: a session edited by hand resumes only if tune would start it
        cfg = build_config(parameters_from_json(json.dumps(s["parameters"]), f"{where}: parameters"), source=where)
        tuning = tuning_from_json(s["tuning"], f"{where}: tuning", cfg)
    except HasControlError as exc:
        raise BagError(f"{exc}; cannot resume") from None
    k, swarm = _last_good_iteration(messages.get(ITERATION) or [], messages.get(SWARM) or [], tuning)
    return tuning, cfg, s.get("evaluator", "batch"), k, swarm


#: What a session may name as its evaluator.
EVALUATORS = ("batch", "dask", "graph")


def _result_ok(r) -> bool:
    """A stored result with what resuming a finished session reads from it."""
    return (isinstance(r, dict) and isinstance(r.get("variant"), str) and isinstance(r.get("seed"), int)
            and not isinstance(r.get("seed"), bool) and isinstance(r.get("seconds"), (int, float))
            and isinstance(r.get("scenarios", 0), int) and isinstance(r.get("aggregate", ""), str))


def _fits(optimiser, tuning: Tuning, k: int) -> bool:
    """Is a restored optimiser the session's after k iterations: its method,
    settings, bounds and seed; for a swarm, P particles of 3 gains everywhere
    (P: swarm.particles)?"""
    if isinstance(optimiser, Restarts):
        return (tuning.method == optimiser.name and optimiser.settings == tuning.restarts
                and optimiser.seed == tuning.seed and optimiser.iteration == k
                and tuple(optimiser.lower) == tuple(tuning.lower) and tuple(optimiser.upper) == tuple(tuning.upper))
    swarm = optimiser
    p = tuning.swarm.particles
    return (swarm.settings == tuning.swarm and swarm.seed == tuning.seed and swarm.iteration == k
            and tuple(swarm.lower) == tuple(tuning.lower) and tuple(swarm.upper) == tuple(tuning.upper)
            and swarm.x.shape == swarm.v.shape == swarm.pbest_x.shape == (p, 3)
            and swarm.pbest_f.shape == (p,) and np.shape(swarm.gbest_x) == (3,)
            and min(swarm.evaluations, swarm.nan_costs) >= 0
            and all(h.positions.shape == (p, 3) and np.shape(h.costs) == (p,) and np.shape(h.best_position) == (3,)
                    for h in swarm.history))


def _last_good_iteration(records, states, tuning: Tuning) -> tuple[int, object | None]:
    """The largest k such that iterations 0..k-1 each have a record and an
    optimiser state that parse and agree, and the optimiser restored from
    state k-1 fits the session's settings (:func:`_fits`)."""
    k = 0
    parsed = []
    for (_, r), (_, x) in zip(records, states):
        rec, state = _json(r), _json(x)
        if rec is None or state is None or rec.get("iteration") != k or state.get("iteration") != k + 1:
            break
        parsed.append((rec, state))
        k += 1
    while k:
        state = dict(parsed[k - 1][1], history=[rec for rec, _ in parsed[:k]])
        try:
            swarm = restore_optimiser(state)
            if (len(swarm.history) == k and all(h.iteration == i for i, h in enumerate(swarm.history))
                    and _fits(swarm, tuning, k)):
                return k, swarm
        except (HasControlError, KeyError, TypeError, ValueError, IndexError, ArithmeticError):
            pass
        k -= 1
    return 0, None


def swarm_result(directory: str | Path):
    """The session's :class:`~has_control.tuning.optimiser.OptimiseResult` rebuilt from its iteration records
    (for the convergence and gain figures)."""
    bag = read_bag(Path(directory) / SESSION, topics=(ITERATION, RESULT), on_warning=lambda m: None)
    try:
        history = [record_from(_json(d)) for _, d in bag.messages.get(ITERATION, [])]
    except (TypeError, KeyError, ValueError, IndexError):
        raise BagError(f"{Path(directory) / SESSION}: an iteration record is damaged") from None
    if not history:
        raise BagError(f"{Path(directory) / SESSION}: no iteration records")
    last = history[-1]
    return OptimiseResult(last.best_position, last.best_cost, len(history),
                          sum(len(h.costs) for h in history), "from the session bag",
                          math.isfinite(last.best_cost), 0, history)


@dataclasses.dataclass
class SessionRun:
    """What a tuning session gave: the result, the keys of ``tune --json``,
    the session bag (None without a directory), its directory and the
    configuration it tuned on (a resumed session's own)."""

    result: TuneResult
    out: dict
    bag: Path | None
    directory: Path | None
    cfg: object = None              # the Config tuned on


def run_session(cfg, tuning: Tuning, directory: str | Path | None = None, *, resume_dir: str | Path | None = None,
                replace: bool = False, evaluator: str = "batch", on_iteration=None,
                record_validation=None, artefacts=None, announce=None, on_warning=warn, batch=None) -> SessionRun:
    """One tuning session, as both front ends run it (``has-control tune`` and the tuner node).

    Opens the session in ``directory`` (or resumes the one in ``resume_dir``
    at its last good iteration; ``cfg`` and ``tuning`` then come from it),
    tunes with the batch evaluator ``batch`` (default: in this process),
    recording every iteration after ``on_iteration(swarm)`` (an observer), and finishes the session: the
    result and the validation run of the best gains under ``/validation``
    (``record_validation(gains, writer, cfg)`` records it, e.g. through the
    node graph; it returns False, or none is given: the in-process trace), ``artefacts(result, directory)``
    (figures), ``gains.yaml`` (a ``--params-file``) and, last, ``tune.json``
    (written then renamed: its presence says the session finished).
    ``announce(message)`` hears what a resume found. ``batch(gains, cfgs)`` has
    the contract of :func:`~has_control.core.episode.evaluate_configs`
    (:class:`~has_control.tuning.dask_evaluator.DaskBatch` on Dask, the tuner
    node's graph evaluator through the lanes; the same bits, so a session may
    resume on another).
    """
    swarm = stored = session = None
    if resume_dir is not None:
        r = resume(resume_dir, on_warning)
        cfg, tuning, swarm, session, stored = r.cfg, r.tuning, r.swarm, r.session, r.result
        directory = resume_dir
        if announce is not None:
            announce(f"resuming {session.path} at iteration {swarm.iteration}, {100 * swarm.progress():.0f} % "
                     f"of {swarm.name}'s budget"
                     + (" (finished; writing its results)" if stored else ""))
    elif directory is not None:
        session = Session(directory, tuning, cfg, evaluator, replace=replace)

    def each_iteration(sw) -> None:
        if on_iteration is not None:
            on_iteration(sw)
        if session is not None:
            session.record(sw)
    try:
        if stored is not None:
            res = TuneResult(stored["variant"], stored["seed"], swarm.result(), stored["seconds"],
                             stored.get("scenarios", 0), stored.get("aggregate", ""),
                             BoundDiagnostics.from_json(stored["bounds"]) if "bounds" in stored else None)
        else:
            res = tune(cfg, tuning, callback=each_iteration, swarm=swarm, batch=batch)
        out = res.as_json()
        bag = None
        if session is not None:
            d = session.directory
            recorded = record_validation is not None and record_validation(res.gains, session.writer, cfg) is not False
            if recorded:
                bag = session.finish(out)
            else:
                bag = session.finish(out, simulate(cfg, res.gains), cfg)
            if artefacts is not None:
                artefacts(res, d)
            write_gains_params(d / "gains.yaml", res.gains, f"has_control tuning: {res.variant}, seed {res.seed}, "
                               f"J = {res.result.fun:.6e}; use with --ros-args --params-file")
            write_atomic(d / RESULT_FILE, json.dumps(out, indent=1) + "\n")
    finally:
        if session is not None:
            session.release()
    return SessionRun(res, out, bag, Path(directory) if directory is not None else None, cfg)
