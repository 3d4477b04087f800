import os
import sys
from pathlib import Path

import pytest
import rclpy

# test modules import each other's helpers (e.g. test_episode.PINNED) as plain modules
sys.path.insert(0, str(Path(__file__).resolve().parent))

# Nodes started by tests discover only this machine, so parallel runs never cross-talk.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

_domain = [100 + os.getpid() % 60]


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
    from has_control.core.params import Config
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
