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
    return _save(fig, path)


def plot_convergence(runs: Sequence[tuple[str, "object"]], path: str | Path) -> Path:
    """Best cost J per iteration, one line per labelled SwarmResult (paper Fig. 6)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, result in runs:
        ax.plot([h.best_cost for h in result.history], lw=1.2, label=label)
    ax.set_xlabel("iteration")
    ax.set_ylabel("best J")
    ax.set_title("Convergence of the fitness J (paper Fig. 6)")
    ax.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    ax.legend()
    fig.tight_layout()
    return _save(fig, path)


def plot_gains(result, path: str | Path, title: str = "") -> Path:
    """Every particle's k1, k2, k3 per iteration, and the best (paper Figs. 3-5)."""
    import numpy as np
    fig, axes = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    its = [h.iteration for h in result.history]
    for d, ax in enumerate(axes):
        for h in result.history:
            if h.positions.size:
                ax.plot(np.full(len(h.positions), h.iteration), h.positions[:, d], ",", color="0.6")
        ax.plot(its, [h.best_position[d] for h in result.history], "C3", lw=1.5, label="best")
        ax.set_ylabel(f"k{d + 1} [1/s]")
    axes[0].set_title(title or "Gains over iterations (paper Figs. 3-5)")
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("iteration")
    fig.tight_layout()
    return _save(fig, path)


def figure_format(path: str | Path) -> str:
    """The format of a figure file, its suffix (none: png); one line naming
    ``path`` if matplotlib writes no such format."""
    from matplotlib.backend_bases import FigureCanvasBase

    from has_control.common.errors import HasControlError
    fmt = Path(path).suffix[1:].lower() or "png"
    known = FigureCanvasBase.get_supported_filetypes()
    if fmt not in known:
        raise HasControlError(f"{path}: a figure cannot be written as '{fmt}' (one of {', '.join(sorted(known))})")
    return fmt


def _save(fig, path) -> Path:
    """Write the figure (then rename: never half a PNG) and close it."""
    from has_control.common.files import write_atomic
    try:
        fmt = figure_format(path)
        return write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=110, format=fmt))
    finally:
        plt.close(fig)


def plot_convergence_spread(groups, path: str | Path) -> Path:
    """Best J per iteration: mean over seeds with the min-max band, one colour per variant."""
    import numpy as np
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label, results in groups:
        n = min(len(r.history) for r in results)
        j = np.array([[h.best_cost for h in r.history[:n]] for r in results])
        line, = ax.plot(j.mean(0), lw=1.3, label=f"{label} (mean of {len(results)})")
        ax.fill_between(range(n), j.min(0), j.max(0), color=line.get_color(), alpha=0.15)
    ax.set_xlabel("iteration")
    ax.set_ylabel("best J")
    ax.set_title("Convergence of J over seeds (paper Fig. 6)")
    ax.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


def plot_robustness(table, path: str | Path) -> Path:
    """J and e_max of each gain set on every scenario (a :class:`~has_control.tuning.robustness.RobustnessTable`),
    scenarios sorted by the first gain set's J; a diverged run is marked at the top of its panel."""
    import numpy as np
    m = table.scores.metrics
    order = np.argsort(np.where(np.isfinite(m[0, :, 0]), m[0, :, 0], np.inf), kind="stable")
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    x = np.arange(len(order))
    for ax, k, name in ((axes[0], 0, "J"), (axes[1], 1, "e_max [m]")):
        finite = m[:, :, k][np.isfinite(m[:, :, k])]
        top = finite.max() * 3 if finite.size else 1.0
        for p, label in enumerate(table.labels):
            v = m[p, order, k]
            ok = np.isfinite(v)
            line, = ax.semilogy(x[ok], v[ok], "o", ms=4, label=label)
            if (~ok).any():
                ax.semilogy(x[~ok], np.full((~ok).sum(), top), "x", ms=7, color=line.get_color(),
                            label=f"{label}: diverged ({(~ok).sum()})")
        ax.set_ylabel(name)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_title(f"Robustness on {m.shape[1]} scenarios (sorted by {table.labels[0]}'s J)")
    axes[0].legend(fontsize=8)
    axes[1].set_xlabel("scenario")
    fig.tight_layout()
    return _save(fig, path)
