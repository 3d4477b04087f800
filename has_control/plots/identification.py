"""Figures of an identification: measured against simulated states."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from has_control.plots.style import BLACK, VERMILLION, WIDTH, label, plt, save, styled


def plot_validation(t: np.ndarray, measured: np.ndarray, simulated: np.ndarray, fit: dict[str, float],
                    path: str | Path, title: str = "") -> Path:
    """Three panels over time t [s]: position y [mm], P1 and P2 [MPa], each
    measured against simulated, with the fit [%] of each in its legend.
    ``measured``, ``simulated``: (n, 4) states (y, ẏ, P1, P2) [m, m/s, Pa, Pa]."""
    with styled():
        fig, axes = plt.subplots(3, 1, figsize=(WIDTH, 7), sharex=True)
        panels = ((0, "y", "mm", 1e3), (2, "P1", "MPa", 1e-6), (3, "P2", "MPa", 1e-6))
        for ax, (k, name, unit, factor) in zip(axes, panels):
            ax.plot(t, measured[:, k] * factor, color=BLACK, lw=0.8, alpha=0.6, label=f"{name} measured")
            ax.plot(t, simulated[:, k] * factor, color=VERMILLION, lw=0.9, ls="--",
                    label=f"{name} simulated (fit {fit.get(name, float('nan')):.2f} %)")
            ax.set_ylabel(label(name, unit))
            ax.legend(loc="upper right")
        axes[0].set_title(title or "Identified model against a recording it was not fitted to")
        axes[-1].set_xlabel(label("time", "s"))
        fig.tight_layout()
    return save(fig, path)
