"""Figures like the paper's (tracking, Fig. 7; error, Fig. 8). matplotlib, Agg backend."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot_tracking(traces: Sequence[tuple[str, "object"]], path: str | Path) -> Path:
    """Two panels: x1d and y over time, and e1 over time, one line per labelled trace."""
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    first = traces[0][1]
    ax1.plot(first["t"], first["x1d"], "k--", lw=1.2, label="x1d (reference)")
    for label, tr in traces:
        ax1.plot(tr["t"], tr["y"], lw=1.0, label=f"y, {label}")
        ax2.plot(tr["t"], tr["e1"], lw=1.0, label=label)
    ax1.set_ylabel("displacement [m]")
    ax1.legend(loc="upper right", fontsize=8)
    ax1.set_title("Displacement tracking (paper Fig. 7)")
    ax2.set_ylabel("e1 = x1d - y [m]")
    ax2.set_xlabel("time [s]")
    ax2.set_title("Tracking error (paper Fig. 8)")
    ax2.legend(loc="upper right", fontsize=8)
    ax2.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
