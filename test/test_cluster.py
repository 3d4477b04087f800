"""The Dask batch evaluator: same bits as evaluate_configs, survives a killed
worker, one-line errors for bad specs and absent schedulers."""
import argparse
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_port, one_line

import has_control
from has_control.cli import main
from has_control.tuning.dask_evaluator import (
    LANES, ClusterError, SpecError, dask_batch, modelled_seconds, parse_spec, plan_tasks,
)
from has_control.config import build_config
from has_control.core.episode import evaluate_configs
from has_control.core.params import Config
from has_control.tuning.tuner import Tuning, tune

WorkerPlugin = pytest.importorskip("distributed").WorkerPlugin

SHORT = {"metrics.skip_start": 0.05, "metrics.skip_end": 0.05}
TREE = Path(has_control.__file__).resolve().parents[1]          # the tree under test
DASK = Path(sys.executable).parent / "dask"                        # the venv's console script


def short_configs(horizon=0.3, amplitudes=(0.05, 0.11, 0.2)):
    return [build_config(dict(SHORT, **{"simulation.horizon": horizon, "reference.amplitude": a}), base=Config())
            for a in amplitudes]


def random_gains(count, seed=0):
    return np.random.default_rng(seed).uniform([150.0, 150.0, 150.0], [1200.0, 800.0, 800.0], size=(count, 3))


# --- specs ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, spec", [
    ("local:2", "local:2"), (" local:02 ", "local:2"), ("LOCAL:1", "local:1"),
    ("tcp://127.0.0.1:8786", "tcp://127.0.0.1:8786"), ("tcp://Node-7.example:8786", "tcp://node-7.example:8786"),
    ("tcp://[::1]:8786", "tcp://[::1]:8786"),
])
def test_parse_spec_normalises(text, spec):
    assert parse_spec(text) == spec


@pytest.mark.parametrize("text, words", [
    ("local:0", "1 <= N"), ("local:x", "whole number"), ("local:", "whole number"), ("local:-1", "whole number"),
    ("local:99999", "1 <= N"), ("ftp://host:21", "unknown scheme 'ftp'"), ("tcp://host", "port"),
    ("tcp://host:0", "port"), ("tcp://host:99999", "port"), ("tcp://:8786", "port"), ("tcp://h:1/x", "port"),
    ("somehost:8786", "expected local:N"), ("", "expected local:N"), (None, "expected local:N"),
])
def test_bad_specs_are_one_line_naming_the_spec(text, words):
    with pytest.raises(SpecError) as err:
        parse_spec(text)
    message = str(err.value)
    assert "\n" not in message and words in message and repr(text) in message
    assert isinstance(err.value, ClusterError) and isinstance(err.value, has_control.common.errors.HasControlError)


def test_bad_spec_through_argparse_is_one_line(capsys):
    parser = argparse.ArgumentParser(prog="has-control")
    parser.add_argument("--dask", type=parse_spec)
    assert parser.parse_args(["--dask", "local:2"]).dask == "local:2"
    with pytest.raises(SystemExit) as done:
        parser.parse_args(["--dask", "local:0"])
    assert done.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "has-control: error: argument --dask: dask spec 'local:0': local:N needs 1 <= N <= 1024 " \
                      "worker processes"
    assert not any("Traceback" in line for line in err)


def test_dask_batch_refuses_a_bad_spec_before_starting_anything():
    for text in ("local:0", "local:x", "ftp://example.org:21"):
        with pytest.raises(SpecError, match="dask spec"):
            dask_batch(text)


@pytest.mark.cluster
def test_unreachable_scheduler_is_one_line_naming_the_address():
    with socket.socket() as s:                                    # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(ClusterError) as err:
        dask_batch(f"tcp://127.0.0.1:{port}", connect_timeout=1.0)
    assert time.monotonic() - t0 < 30
    message = str(err.value)
    assert "\n" not in message and f"tcp://127.0.0.1:{port}" in message and "no Dask scheduler" in message


def test_cluster_module_imports_no_ros_and_no_dask():
    code = ("import sys, has_control.tuning.dask_evaluator\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'rosbags', 'mcap', 'distributed', 'dask')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# --- the chunk plan -------------------------------------------------------------------------------

@pytest.mark.parametrize("candidates, scenarios, samples, nthreads", [
    (80, 1, 33_334, [1, 1]), (80, 20, 33_334, [1, 1]), (80, 100, 33_334, [1] * 64), (80, 1, 33_334, [1] * 512),
    (16, 1, 1_667, [1, 1]), (20, 3, 1_000, [1, 1]), (5, 2, 100, [1]), (1000, 3, 33_334, [4, 4, 4]),
    (81, 7, 33_334, [2, 2]), (1, 1, 10, [8]),
])
def test_plan_covers_every_row_once_in_whole_units(candidates, scenarios, samples, nthreads):
    tasks = plan_tasks(candidates, [samples] * scenarios, nthreads)
    covered = np.zeros((candidates, scenarios), dtype=int)
    unit = LANES * max(nthreads)
    for s, lo, hi in tasks:
        assert 0 <= lo < hi <= candidates
        assert lo % unit == 0 and (hi % unit == 0 or hi == candidates)
        covered[lo:hi, s] += 1
    assert (covered == 1).all()
    assert tasks == sorted(tasks)


def test_plan_follows_the_model():
    b = 33_334 * 2.0e-7                                            # one 10 s block [s]
    paper = plan_tasks(80, [33_334], [1, 1])                      # 10 blocks on 2 workers: 5 each
    assert [hi - lo for _, lo, hi in paper] == [40, 40]
    assert len(plan_tasks(80, [33_334] * 20, [1, 1])) == 20      # enough scenarios: one task each
    wide = plan_tasks(80, [33_334], [1] * 512)                    # at most 10 blocks of work exist
    assert len(wide) == 10
    assert modelled_seconds(10, 1, 10, 512, b) < modelled_seconds(1, 1, 10, 512, b)
    assert plan_tasks(0, [100], [1]) == [] and plan_tasks(8, [], [1]) == []


# --- on a cluster ---------------------------------------------------------------------------------

@pytest.mark.cluster
def test_local_cluster_gives_the_bits_of_evaluate_configs():
    cfgs = short_configs()
    gains = random_gains(20)
    gains[3] = [1.0e6, 1.0e6, 1.0e6]                                # diverges: +inf rows travel too
    expected = evaluate_configs(gains, cfgs)
    with dask_batch("local:2") as batch:
        assert sum(batch.client.nthreads().values()) == 2
        got = batch(gains, cfgs)
        again = batch(gains[::-1], cfgs[::-1])                      # other rows, other tasks, same configs
        empty = batch(np.empty((0, 3)), cfgs)
    assert got.shape == (20, 3, 4) and got.dtype == np.float64
    assert np.array_equal(got, expected)
    assert np.array_equal(again, expected[::-1, ::-1])
    assert empty.shape == (0, 3, 4)
    assert batch.client is None and batch.cluster is None          # closed on exit
    with pytest.raises(ClusterError, match="closed"):
        batch(gains, cfgs)


@pytest.mark.cluster
def test_a_worker_with_other_bits_is_refused(monkeypatch):
    """The warm-up compares every worker's probe with this process's: here
    this process pretends to compute other bits (a different kernel or libm)."""
    import has_control.tuning.dask_evaluator as cluster

    def off_by_one_ulp(gains, cfgs, workers=None):
        return np.nextafter(evaluate_configs(gains, cfgs, workers), np.inf)
    monkeypatch.setattr(cluster, "evaluate_configs", off_by_one_ulp)
    with pytest.raises(ClusterError) as err:
        dask_batch("local:1")
    message = str(err.value)
    assert "\n" not in message and "computes other bits than this process" in message


class KillOnceArmed(WorkerPlugin):
    """A worker plugin: the first worker to start a chunk task after ``armed``
    exists writes its pid to ``claimed`` and SIGKILLs itself, mid-task."""

    def __init__(self, armed: str, claimed: str):
        self.armed, self.claimed = armed, claimed

    def transition(self, key, start, finish, **kwargs):
        if finish != "executing" or "evaluate_chunk" not in str(key) or not os.path.exists(self.armed):
            return
        try:
            fd = os.open(self.claimed, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        os.kill(os.getpid(), signal.SIGKILL)


@pytest.mark.cluster
def test_a_lost_scheduler_is_one_line(dask_processes):
    """The scheduler dies between calls: the client tries to reconnect for
    connect_timeout, then the call fails with one line naming the address."""
    address, scheduler, _ = dask_processes
    cfgs = short_configs()[:1]
    with dask_batch(address, connect_timeout=3.0, worker_timeout=120.0, min_workers=2) as batch:
        assert batch(random_gains(8), cfgs).shape == (8, 1, 4)
        scheduler.kill()
        scheduler.wait(30)
        with pytest.raises(ClusterError) as err:
            batch(random_gains(8), cfgs)
        with pytest.raises(ClusterError) as again:                    # and so does every later call
            batch(random_gains(8), cfgs)
    for message in (str(err.value), str(again.value)):
        assert "\n" not in message and address in message and "lost the cluster" in message


@pytest.mark.cluster
def test_a_restarted_local_worker_gets_the_configs_and_reruns_the_task(tmp_path):
    """local:1: the only worker dies mid-task; its nanny restarts it, the
    Config store reaches it as it registers, the task runs again."""
    import cloudpickle
    cfgs = short_configs()
    gains = random_gains(20)
    armed, claimed = tmp_path / "armed", tmp_path / "claimed"
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        with dask_batch("local:1") as batch:
            first = batch(gains, cfgs)
            (old,) = batch.client.nthreads()
            batch.client.register_plugin(KillOnceArmed(str(armed), str(claimed)), name="kill-once-armed")
            armed.touch()
            second = batch(gains, cfgs)
            (new,) = batch.client.nthreads()
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert claimed.exists() and old != new
    assert np.array_equal(first, evaluate_configs(gains, cfgs)) and np.array_equal(second, first)


def _wait_for_port(port: int, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    """Until something accepts connections on 127.0.0.1:port (the scheduler has started)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"dask scheduler on port {port} did not start (exit status {proc.poll()})")


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


@pytest.fixture
def dask_processes(tmp_path, request):
    """``dask scheduler`` and two ``dask worker --nthreads 1 --no-nanny`` on
    127.0.0.1, importing the tree under test; stopped whatever happens.
    Yields (address, scheduler process, {pid: worker process})."""
    if not DASK.exists():
        pytest.skip(f"no dask console script at {DASK}")
    path = [str(TREE)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else [])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(path))
    env.setdefault("NUMBA_CACHE_DIR", str(TREE / ".numba-cache"))
    procs = []

    def start(name, args):
        log = open(tmp_path / f"{name}.log", "wb")
        procs.append(subprocess.Popen([str(DASK), *args], env=env, stdout=log, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, cwd=tmp_path))
        log.close()
        return procs[-1]

    def stop_all():
        for proc in reversed(procs):
            _stop(proc)
    request.addfinalizer(stop_all)
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"])
    _wait_for_port(port, scheduler)
    workers = [start(f"worker{i}", ["worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                                    "--host", "127.0.0.1", "--name", f"w{i}", "--death-timeout", "120"])
               for i in range(2)]
    yield address, scheduler, {w.pid: w for w in workers}


@pytest.mark.cluster
def test_tune_through_dask_survives_a_worker_killed_mid_task(dask_processes, tmp_path):
    """A worker SIGKILLed while it runs a task of the second iteration costs
    time, not results: the scheduler reruns the task on the other worker and
    the tuning ends with the gains, cost and history of a run without Dask."""
    import cloudpickle
    address, _, workers = dask_processes
    cfg = build_config(dict(SHORT, **{"simulation.horizon": 0.5}), base=Config())
    tuning = Tuning().replace(variant="pso-cp-tvac", particles=16, iterations=4)
    expected = tune(cfg, tuning)
    armed, claimed = tmp_path / "armed", tmp_path / "claimed"
    calls = []
    cloudpickle.register_pickle_by_value(sys.modules[__name__])     # the plugin travels by value
    try:
        with dask_batch(address, connect_timeout=60.0, worker_timeout=120.0, min_workers=2) as batch:
            batch.client.wait_for_workers(2, timeout=120)               # (dask_batch waited and warmed both)
            batch.client.register_plugin(KillOnceArmed(str(armed), str(claimed)), name="kill-once-armed")

            def arming_batch(gains, cfgs):
                out = batch(gains, cfgs)
                calls.append(len(gains))
                armed.touch()                    # from the second call on, a worker dies in its first task
                return out
            got = tune(cfg, tuning, batch=arming_batch)
            remaining = batch.client.nthreads()
            rescheduled = batch.client.run_on_scheduler(
                lambda dask_scheduler: dask_scheduler.task_prefixes["evaluate_chunk"].suspicious)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    victim = int(claimed.read_text())
    assert victim in workers and workers[victim].wait(30) == -signal.SIGKILL
    assert len(remaining) == 1 and rescheduled >= 1
    assert len(calls) >= 2 and sum(calls) == expected.result.nfev
    assert got.gains == expected.gains
    assert got.result.fun == expected.result.fun
    assert [h.best_cost for h in got.result.history] == [h.best_cost for h in expected.result.history]
    assert got.result.nfev == expected.result.nfev


def test_scaling_model_of_the_bench():
    from has_control.bench.dask import LAYOUTS, dask_scaling
    rows = dask_scaling(7.2e-3, 0.9e-3, 0.5e-3, 4.4e-3)
    assert len(rows) == 2 * len(LAYOUTS)
    paper = {(r["workers"], r["threads"]): r for r in rows if r["case"] == "paper"}
    assert paper[(64, 1)]["tasks"] == 10                           # one block a task: all an iteration has
    assert paper[(512, 1)]["iteration_seconds"] == paper[(64, 1)]["iteration_seconds"]
    assert all(0 < r["efficiency"] <= 1 for r in rows)


@pytest.mark.cluster
def test_cli_robust_tuning_on_dask_equals_the_local_one(capsys):
    """Robust tuning on Dask: ``tune --scenarios config/scenarios.yaml --aggregate cvar:0.2
    --dask local:2 --json`` gives the result it gives without --dask (a short run of it)."""
    from has_control.cli import main
    from has_control.config import CONFIG_DIR
    args = ["tune", "--scenarios", str(CONFIG_DIR / "scenarios.yaml"), "--aggregate", "cvar:0.2",
            "--variant", "pso-cp-tvac", "--particles", "16", "--iterations", "3", "--duration", "1.2", "--json"]
    outs = []
    for extra in ([], ["--dask", "local:2"]):
        assert main(args + extra) == 0
        out = capsys.readouterr().out
        doc = __import__("json").loads(out)
        doc.pop("seconds")
        outs.append(doc)
    assert outs[0] == outs[1] and outs[0]["scenarios"] == 20 and outs[0]["aggregate"] == "cvar:0.2"


@pytest.mark.cluster
def test_a_session_started_on_dask_resumes_locally_to_the_same_result(tmp_path):
    """Sessions stay resumable: the evaluator is not part of the result, so a
    session interrupted on a cluster finishes in-process with the same bits."""
    from has_control.core.scenarios import parse_aggregate
    from has_control.config import Scenario
    from has_control.tuning.session import run_session
    cfg = build_config({"simulation.horizon": 1.2}, base=Config())
    t = Tuning().replace(variant="pso-cp-tvac", particles=8, iterations=4, aggregate=parse_aggregate("max"),
                         scenarios=(Scenario("nominal"), Scenario("heavy", (("plant.mass", 1800.0),))))
    whole = tune(cfg, t)

    def stop_after_two(swarm):
        if swarm.iteration == 2:
            raise KeyboardInterrupt
    with dask_batch("local:2") as batch, pytest.raises(KeyboardInterrupt):
        run_session(cfg, t, tmp_path / "s", on_iteration=stop_after_two, batch=batch, evaluator="dask")
    resumed = run_session(None, None, resume_dir=tmp_path / "s")
    assert resumed.result.gains == whole.gains and resumed.result.result.fun == whole.result.fun
    assert [h.best_cost for h in resumed.result.result.history] == [h.best_cost for h in whole.result.history]


def _server(behaviour):
    """A listener on 127.0.0.1 that is not a Dask scheduler; its port."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(8)
    held = []

    def serve():
        while True:
            try:
                c, _ = s.accept()
            except OSError:
                return
            held.append(c)
            try:
                if behaviour == "garbage":
                    c.sendall(bytes(range(256)) * 16 + b"\xff" * 64)
                elif behaviour == "http":
                    c.recv(1024)
                    c.sendall(b"HTTP/1.0 400 Bad Request\r\n\r\n")
            except OSError:
                pass
    threading.Thread(target=serve, daemon=True).start()
    return s, s.getsockname()[1]


@pytest.mark.cluster
@pytest.mark.parametrize("behaviour", ["silent", "garbage", "http"])
def test_an_address_that_is_not_a_scheduler_is_one_line(behaviour, capsys):
    pytest.importorskip("distributed")
    server, port = _server(behaviour)
    old = signal.signal(signal.SIGALRM, lambda *a: pytest.fail("hangs"))
    signal.alarm(60)                                       # a hang guard, not a timing
    try:
        one_line(capsys, ["tune", "--variant", "pso-cp-tvac",
                          "--particles", "2", "--iterations", "1", "--duration", "1.2",
                          "--dask", f"tcp://127.0.0.1:{port}"], f"tcp://127.0.0.1:{port}", "scheduler")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
        server.close()


def test_a_huge_worker_count_is_cut_in_the_error(capsys):
    with pytest.raises(SystemExit):
        main(["tune", "--dask", "local:" + "9" * 5000])
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and len(err) < 300 and "1 <= N <= 1024" in err, err
