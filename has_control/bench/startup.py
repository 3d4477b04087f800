"""Start-up: a warm ``has-control simulate --duration 2 --json`` against
``python -c "import numba, numpy"`` (the floor: what any numba program pays),
best of N fresh interpreters each, alternated, the ratio in the same run."""
from __future__ import annotations

import subprocess
import sys
import time

#: The commands compared: (label, argv).
COMMANDS = (("python -c 'import numba, numpy'", [sys.executable, "-c", "import numba, numpy"]),
            ("has-control simulate --duration 2 --json",
             [sys.executable, "-m", "has_control.cli", "simulate", "--duration", "2", "--json"]))


def _seconds(argv) -> float:
    t = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def bench_startup(repeats: int = 3) -> dict:
    """Best wall time [s] of each command over ``repeats`` alternating runs (one warm-up run each first)."""
    for _, argv in COMMANDS:
        _seconds(argv)                               # warm: numba's cache, the OS's file cache
    best = {label: float("inf") for label, _ in COMMANDS}
    for _ in range(repeats):
        for label, argv in COMMANDS:
            best[label] = min(best[label], _seconds(argv))
    floor, ours = (best[label] for label, _ in COMMANDS)
    return {"seconds": best, "ratio": ours / floor}


def print_startup(r: dict, repeats: int) -> None:
    print(f"start-up, best of {repeats} fresh interpreters (warm caches):")
    for label, s in r["seconds"].items():
        print(f"  {label:45s} {s:.3f} s")
    print(f"  simulate / import numba, numpy: {r['ratio']:.2f}x (target <= 1.5x)")
