"""has_control: simulation, adaptive back-stepping control and PSO gain tuning
of a hydraulic active-suspension actuator."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: Modules whose compiled functions call one another (params holds the index
#: constants the kernels bake in).
COMPILED_MODULES = ("core.jit", "core.params", "core.actuator", "core.road", "core.reference",
                    "core.abc_controller", "core.cost", "core.noise", "core.episode", "wire.cdr", "wire.codec",
                    "wire.topics", "wire.steps")


def _load_compiled_modules() -> None:
    """Import the compiled core with numba's cache keyed by all of its sources.

    numba's ``cache=True`` invalidates a function only when its own file
    changes, not when a function it calls in another module does; an edit to
    the physics would then silently run a stale kernel. A cache directory per
    hash of every compiled module makes any such edit recompile everything.
    numba's own setting is restored afterwards, so other numba users in the
    process keep theirs; an unwritable directory falls back to numba's default.
    """
    import importlib

    import numba

    here = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for name in COMPILED_MODULES:
        digest.update((here / f"{name.replace('.', '/')}.py").read_bytes())
    previous = numba.config.CACHE_DIR
    base = previous or str(here / "__pycache__")
    numba.config.CACHE_DIR = os.path.join(base, f"has_control-{digest.hexdigest()[:16]}")
    try:
        for name in COMPILED_MODULES:
            importlib.import_module(f"{__name__}.{name}")
    finally:
        numba.config.CACHE_DIR = previous


def _exit_quietly_on_interrupt(signum, frame):
    """Leave at once: an exception raised inside a C extension's import (numpy,
    numba) would be turned into an ImportError with a traceback."""
    os.write(2, b"has-control: interrupted\n")
    os._exit(130)


def raise_interrupt(signum, frame):
    """A SIGTERM handler: end as Ctrl-C does (``has_control.cli.main`` installs it)."""
    raise KeyboardInterrupt


class quiet_interrupts:
    """A context in which Ctrl-C or SIGTERM ends the process at once with one
    line and status 130 (as ``has_control.cli.main`` ends an interrupted
    command): for loading code (imports, numba's cache), where a
    KeyboardInterrupt would surface as an ImportError or an "Exception
    ignored" from a ctypes callback instead, and SIGTERM's default action
    would end the process silently. Each signal only while its handler is
    Python's default (main thread, nobody else's); restored on exit."""

    def __enter__(self):
        import signal
        import threading
        main = threading.current_thread() is threading.main_thread()
        defaults = {signal.SIGINT: (signal.default_int_handler,), signal.SIGTERM: (signal.SIG_DFL, raise_interrupt)}
        self.ours = {sig: signal.getsignal(sig) for sig, hs in defaults.items() if main and signal.getsignal(sig) in hs}
        for sig in self.ours:
            signal.signal(sig, _exit_quietly_on_interrupt)
        return self

    def __exit__(self, *exc):
        import signal
        for sig, handler in self.ours.items():
            signal.signal(sig, handler)


with quiet_interrupts():        # the first second of every command, before cli.main can catch anything
    _load_compiled_modules()
    # The public API, in groups (the package's own modules, loaded after the compiled core).

    # Parameters and configuration files
    from has_control.config import (  # noqa: E402,F401
        build_config, load_config, load_scenarios, with_horizon,
    )
    from has_control.core.params import (  # noqa: E402,F401
        Actuator, Adaptation, Config, Episode, Gains, Noise, Plant, Reference,
    )

    # Simulation and evaluation
    from has_control.core.episode import Col, Trace, evaluate, evaluate_configs, simulate  # noqa: E402,F401
    from has_control.core.scenarios import Aggregate, ScenarioScores, parse_aggregate  # noqa: E402,F401

    # Tuning
    from has_control.tuning.methods import METHODS, minimize  # noqa: E402,F401
    from has_control.tuning.restarts import RestartSettings, Restarts  # noqa: E402,F401
    from has_control.tuning.swarm import Swarm, SwarmResult, SwarmSettings  # noqa: E402,F401
    from has_control.tuning.tuner import Tuning, load_tuning, tune  # noqa: E402,F401
