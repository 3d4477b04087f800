"""has_control: simulation, adaptive back-stepping control and PSO gain tuning
of a hydraulic active-suspension actuator.

Importing the package costs almost nothing: the public API below loads on
first use, the compiled core (and numba) when a module of it is imported, and
no signal policy is installed (``has_control.cli`` installs its own, from
``has_control.common.interrupts``)."""
from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

#: Modules whose compiled functions call one another (params holds the index
#: constants the kernels bake in).
COMPILED_MODULES = ("core.jit", "core.params", "core.actuator", "core.road", "core.reference",
                    "core.abc_controller", "core.cost", "core.measures", "core.noise", "core.episode", "wire.cdr",
                    "wire.codec", "wire.topics", "wire.steps", "identify.data", "identify.kernel",
                    "deploy.watchdog", "deploy.stepping", "deploy.guarded")


def _cache_key() -> str:
    """The hash of every compiled module's source (computed once, at the first compiled import)."""
    global _KEY
    if _KEY is None:
        here = Path(__file__).resolve().parent
        digest = hashlib.sha256()
        for name in COMPILED_MODULES:
            digest.update((here / f"{name.replace('.', '/')}.py").read_bytes())
        _KEY = digest.hexdigest()[:16]
    return _KEY


_KEY: str | None = None
_COMPILED = frozenset(f"{__name__}.{name}" for name in COMPILED_MODULES)


class _KeyedLoader:
    """Runs a compiled module with numba's cache keyed by all of their sources.

    numba's ``cache=True`` invalidates a function only when its own file
    changes, not when a function it calls in another module does; an edit to
    the physics would then silently run a stale kernel. A cache directory per
    hash of every compiled module makes any such edit recompile everything.
    numba's own setting is restored after the module has run (its functions
    took their cache locations when defined), so other numba users in the
    process keep theirs. Nothing of this happens until a compiled module is
    imported: ``import has_control`` alone loads neither numba nor a kernel.
    """

    def __init__(self, loader):
        self.loader = loader

    def __getattr__(self, name):                  # get_source, get_filename, ... : the real loader's
        return getattr(self.loader, name)

    def create_module(self, spec):
        return self.loader.create_module(spec)

    def exec_module(self, module) -> None:
        import numba
        previous = numba.config.CACHE_DIR
        base = previous or str(Path(__file__).resolve().parent / "__pycache__")
        numba.config.CACHE_DIR = os.path.join(base, f"has_control-{_cache_key()}")
        try:
            self.loader.exec_module(module)
        finally:
            numba.config.CACHE_DIR = previous


class _KeyedFinder:
    """The import hook that gives every module of :data:`COMPILED_MODULES` a :class:`_KeyedLoader`."""

    @staticmethod
    def find_spec(name, path=None, target=None):
        if name not in _COMPILED:
            return None
        from importlib.machinery import PathFinder
        spec = PathFinder.find_spec(name, path, target)
        if spec is not None and spec.loader is not None:
            spec.loader = _KeyedLoader(spec.loader)
        return spec


if not any(isinstance(f, _KeyedFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _KeyedFinder())


#: The public API: name -> the module that defines it (loaded on first use, PEP 562).
_API = {
    # Parameters and configuration files
    **dict.fromkeys(("build_config", "load_config", "load_scenarios", "with_horizon"), "config"),
    **dict.fromkeys(("Actuator", "Adaptation", "Config", "Episode", "Gains", "Noise", "Plant", "Reference"),
                    "core.params"),
    # Simulation and evaluation
    **dict.fromkeys(("Col", "Trace", "evaluate", "evaluate_configs", "simulate"), "core.episode"),
    **dict.fromkeys(("Aggregate", "ScenarioScores", "parse_aggregate"), "core.scenarios"),
    # Tuning
    **dict.fromkeys(("METHODS", "minimize"), "tuning.methods"),
    **dict.fromkeys(("RestartSettings", "Restarts"), "tuning.restarts"),
    **dict.fromkeys(("Swarm", "SwarmResult", "SwarmSettings"), "tuning.swarm"),
    **dict.fromkeys(("Tuning", "load_tuning", "tune"), "tuning.tuner"),
}


def __getattr__(name: str):
    if name == "__version__":                    # setup.py's version, one home
        from has_control.common.version import package_version     # lazy: on first use only (PEP 562)
        globals()[name] = value = package_version()
        return value
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module
    value = getattr(import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_API) | {"__version__"})
