"""has_control: simulation, adaptive back-stepping control and PSO gain tuning
of a hydraulic active-suspension actuator."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: Modules whose compiled functions call one another (params holds the index
#: constants the kernels bake in).
COMPILED_MODULES = ("jit", "params", "cdr", "wire", "topics", "actuator", "reference", "abc_controller", "cost",
                    "episode", "loop")


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
        digest.update((here / f"{name}.py").read_bytes())
    previous = numba.config.CACHE_DIR
    base = previous or str(here / "__pycache__")
    numba.config.CACHE_DIR = os.path.join(base, f"has_control-{digest.hexdigest()[:16]}")
    try:
        for name in COMPILED_MODULES:
            importlib.import_module(f"{__name__}.{name}")
    finally:
        numba.config.CACHE_DIR = previous


def _exit_quietly_on_interrupt(signum, frame):
    import sys
    print("has-control: interrupted", file=sys.stderr)
    raise SystemExit(130)


def _load_quietly() -> None:
    """:func:`_load_compiled_modules`, with Ctrl-C during it (the first second
    of every command, before ``cli.main`` can catch anything) ending the
    process with one line and status 130 instead of a traceback. Only when
    Python's own SIGINT handler is in place (main thread, nobody else's)."""
    import signal
    import threading
    ours = (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is signal.default_int_handler)
    if ours:
        signal.signal(signal.SIGINT, _exit_quietly_on_interrupt)
    try:
        _load_compiled_modules()
    finally:
        if ours:
            signal.signal(signal.SIGINT, signal.default_int_handler)


_load_quietly()
