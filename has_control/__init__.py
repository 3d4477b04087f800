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


_load_compiled_modules()
