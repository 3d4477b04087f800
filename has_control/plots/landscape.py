"""Heatmaps of the tuning objective over 2-D slices of the gain space
(``has-control landscape``): J relative to the slice's best, the box's bound,
the grid's local minima and the point the slices pass through."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from has_control.plots.style import label, plt, save, styled

NAMES = ("k1", "k2", "k3")


def plot_landscape(slices: Sequence, path: str | Path, title: str = "") -> Path:
    """One panel per slice (a :class:`has_control.tuning.landscape.Slice`):
    log10(J / J_best) as colour, the box's upper bounds dashed, local minima
    (o, the best filled), the point (*) and, beyond the box, the slice's best (x)."""
    with styled():
        fig = _draw(slices, title)
    return save(fig, path)


def _draw(slices: Sequence, title: str):
    fig, axes = plt.subplots(1, len(slices), figsize=(4.2 * len(slices), 3.9), squeeze=False)
    for ax, s in zip(axes[0], slices):
        i, j = s.axes
        J = np.where(np.isfinite(s.J), s.J, np.nan)
        best = np.nanmin(J)
        rel = np.log10(J / best)
        mesh = ax.pcolormesh(s.xj, s.xi, rel, shading="nearest", cmap="viridis",
                             vmin=0.0, vmax=max(1e-6, float(np.nanpercentile(rel, 90))))
        ax.contour(s.xj, s.xi, rel, levels=[0.002, 0.01, 0.05], colors="w", linewidths=0.5)
        ax.add_patch(plt.Rectangle((s.lower[1], s.lower[0]), s.upper[1] - s.lower[1], s.upper[0] - s.lower[0],
                                   fill=False, ls="--", lw=1.2, ec="r", label="bound of the box"))
        minima = s.minima()
        if minima:
            ax.plot([m[1] for m in minima], [m[0] for m in minima], "o", mfc="none", mec="w", ms=6,
                    label=f"local minima ({len(minima)})")
            ax.plot([minima[0][1]], [minima[0][0]], "o", color="w", ms=6)
        ax.plot([s.point[j]], [s.point[i]], "*", color="orange", ms=11, mec="k", label="point")
        bi, bj, _ = s.best()
        if not (s.lower[0] <= bi <= s.upper[0] and s.lower[1] <= bj <= s.upper[1]):
            ax.plot([bj], [bi], "x", color="r", ms=9, mew=2, label="lowest J: outside the box")
        k = 3 - i - j
        ax.set_xlabel(label(NAMES[j], "1/s"))
        ax.set_ylabel(label(NAMES[i], "1/s"))
        ax.set_title(f"{NAMES[k]} = {s.point[k]:.1f}", fontsize=9)
        fig.colorbar(mesh, ax=ax, label=label("log10(J / J_min of the slice)", "1"))
    axes[0][0].legend(loc="lower right", fontsize=7, framealpha=0.6)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
