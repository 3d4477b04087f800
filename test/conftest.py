import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import rclpy

from has_control.cli import main
from has_control.config import with_horizon
from has_control.core.params import Config
from has_control.nodes.stack import run_stack

# test modules import each other's helpers (e.g. test_episode.PINNED) as plain modules
sys.path.insert(0, str(Path(__file__).resolve().parent))

# Nodes started by tests discover only this machine, so parallel runs never cross-talk.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

_domain = [100 + os.getpid() % 60]

#: A scenario file of two scenarios: the nominal plant and a heavy one (1 800 kg).
NOM = "scenarios:\n  nominal: {}\n  heavy: {plant.mass: 1800.0}\n"

#: The command line on a real interpreter (``python -m has_control.cli``): for the few tests that prove
#: the entry point, a signal or a second process; argument checks call ``has_control.cli.main`` in-process.
CLI = [sys.executable, "-m", "has_control.cli"]


@pytest.fixture
def domain_id():
    """A ROS domain of its own for each test that starts nodes (ids 100..229)."""
    _domain[0] = 100 + (_domain[0] - 99) % 130
    return _domain[0]


@pytest.fixture
def context(domain_id):
    """An rclpy context of its own, on the test's domain."""
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture(scope="session")
def recorded(tmp_path_factory):
    """One 1.5 s lock-step run of the reference configuration through the nodes, recorded as
    ``stack --record`` records it (ROS domain of its own): (bag directory, Config, StackRun).
    Run once per session; tests only read it (a test that changes a bag copies it first)."""
    d = tmp_path_factory.mktemp("bags") / "run"
    cfg = with_horizon(Config(), 1.5)
    run = run_stack(cfg, record=d, domain_id=231 if os.getpid() % 2 else 232)   # domain_id hands out 100..229
    return d, cfg, run


def pytest_collection_modifyitems(config, items):
    """The long runs (marker ``slow``) only when ``-m`` names them: any other
    ``-m`` expression (e.g. ``-m "not ros"``) still leaves them out."""
    if "slow" in (config.option.markexpr or ""):
        return
    slow = [i for i in items if i.get_closest_marker("slow")]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [i for i in items if not i.get_closest_marker("slow")]


def stopped_session(directory, particles: int, iterations: int, stop_after: int = 2, horizon: float = 1.2):
    """A pso-cp-tvac session in ``directory`` of ``particles`` x ``iterations``,
    stopped (its bag closed) after ``stop_after`` iterations, as a kill leaves it."""
    from has_control.config import with_horizon
    from has_control.core.params import Config           # and rclpy load only then
    from has_control.tuning.session import Session
    from has_control.tuning.tuner import load_tuning, tune
    cfg = with_horizon(Config(), horizon)
    tuning = load_tuning().replace(variant="pso-cp-tvac", particles=particles, iterations=iterations)
    session = Session(directory, tuning, cfg)

    class Stop(Exception):
        pass

    def each(sw):
        session.record(sw)
        if sw.iteration == stop_after:
            raise Stop
    with pytest.raises(Stop):
        tune(cfg, tuning, callback=each)
    session.close()
    session.release()
    return directory


# --- helpers the test modules share (``from conftest import ...``) ---------------------------------

def cli(*args, domain=None, timeout=900, **kw):
    """``has-control *args`` in a subprocess (on ROS domain ``domain`` if given): its CompletedProcess."""
    env = dict(kw.pop("env", None) or os.environ)
    if domain is not None:
        env["ROS_DOMAIN_ID"] = str(domain)
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout, env=env, **kw)


def run_main(capsys, *args):
    """``has-control *args`` in this process (``has_control.cli.main``), as ``cli`` runs it in a subprocess:
    an object with returncode (SystemExit's code for the argument parser's refusals), stdout and stderr."""
    try:
        code = main([str(a) for a in args])
    except SystemExit as exit_:
        code = exit_.code
    cap = capsys.readouterr()
    return SimpleNamespace(returncode=code, stdout=cap.out, stderr=cap.err)


def main_result(capsys, *argv):
    """``has_control.cli.main(argv)`` in this process: (status, stdout, stderr)."""
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def one_error_line(rc, err, *culprits, code=2, warnings=False):
    """Status ``rc`` is ``code`` and ``err`` is one line naming ``culprits``, no traceback
    (``warnings``: besides lines "warning: ..." that say what was found)."""
    assert rc == code, err
    lines = [x for x in err.strip().splitlines() if not (warnings and "has-control: warning:" in x)]
    assert len(lines) == 1 and "Traceback" not in err, err
    for c in culprits:
        assert str(c) in err, err
    return err


def one_line(capsys, argv, *culprits, code=2, warnings=False):
    """``has_control.cli.main(argv)`` in-process ends with status ``code`` and one line on
    stderr naming ``culprits``; that stderr."""
    rc = main([str(a) for a in argv])
    return one_error_line(rc, capsys.readouterr().err, *culprits, code=code, warnings=warnings)


def argparse_error(capsys, argv, *culprits):
    """``argv`` is refused by the argument parser: SystemExit 2 and one line naming ``culprits``."""
    with pytest.raises(SystemExit) as info:
        main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert info.value.code == 2 and len(err.strip().splitlines()) == 1, err
    for c in culprits:
        assert str(c) in err, err
    return err


def spin_until(ex, cond, seconds, step=0.01):
    """Spin executor ``ex`` until ``cond()`` holds or ``seconds`` [s] pass; ``cond()``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end and not cond():
        ex.spin_once(timeout_sec=step)
    return cond()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (now)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
