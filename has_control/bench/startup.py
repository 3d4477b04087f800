"""Start-up: a warm ``has-control simulate --duration 2 --json`` against
``python -c "import numba, numpy"`` (what the issue measures against) and
against one cached ``@njit`` call (what any program that runs a compiled
function pays: numba initialises its CPU target at the first call, which
imports ``numba.np.arraymath`` and through it ``scipy.linalg``), best of N
fresh interpreters each, alternated, the ratios in the same run."""
from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

_ONE_KERNEL = ("import sys, numba\n"
               "sys.path.insert(0, sys.argv[1])\n"
               "@numba.njit(cache=True)\n"
               "def one(x):\n"
               "    return x + 1.0\n"
               "one(1.0)\n")
#: The commands compared: (label, argv); the last is ours.
COMMANDS = (("python -c 'import numba, numpy'", [sys.executable, "-c", "import numba, numpy"]),
            ("one cached @njit call", None),
            ("has-control simulate --duration 2 --json",
             [sys.executable, "-m", "has_control.cli", "simulate", "--duration", "2", "--json"]))


def _seconds(argv) -> float:
    t = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def bench_startup(repeats: int = 3) -> dict:
    """Best wall time [s] of each command over ``repeats`` alternating runs (one warm-up run each first)."""
    with tempfile.TemporaryDirectory() as d:
        script = Path(d) / "one_kernel.py"
        script.write_text(_ONE_KERNEL)
        commands = [(label, argv or [sys.executable, str(script), d]) for label, argv in COMMANDS]
        for _, argv in commands:
            _seconds(argv)                               # warm: numba's cache, the OS's file cache
        best = {label: float("inf") for label, _ in commands}
        for _ in range(repeats):
            for label, argv in commands:
                best[label] = min(best[label], _seconds(argv))
    imports, kernel, ours = (best[label] for label, _ in commands)
    return {"seconds": best, "ratio": ours / imports, "ratio_kernel": ours / kernel}


def print_startup(r: dict, repeats: int) -> None:
    print(f"start-up, best of {repeats} fresh interpreters (warm caches):")
    for label, s in r["seconds"].items():
        print(f"  {label:45s} {s:.3f} s")
    print(f"  simulate / import numba, numpy: {r['ratio']:.2f}x (target <= 1.5x)")
    print(f"  simulate / one cached @njit call: {r['ratio_kernel']:.2f}x")
