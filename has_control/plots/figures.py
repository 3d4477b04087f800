"""The tuning figures (the paper's Figs. 3-6) and the robustness figure, in the house style.

A run's time series (the paper's Figs. 7-8 and more) is :mod:`has_control.plots.run_figure`'s.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import matplotlib.pyplot as plt

from has_control.plots.style import (  # noqa: F401  (figure_format: re-exported for the CLI)
    BLACK, WIDTH, colour, figure_format, label, save, styled,
)

#: J's unit: Σ(λ1|e1| + λ2·u² + λ3|e1|·[e1 < 0])·Δt with e1, u in metres (SPEC §6).
J_UNIT = "m·s + m²·s"


def plot_convergence(runs: Sequence[tuple[str, "object"]], path: str | Path) -> Path:
    """Best cost J per iteration, one line per labelled SwarmResult (paper Fig. 6)."""
    with styled():
        fig, ax = plt.subplots(figsize=(WIDTH, 4.0))
        for label_, result in runs:
            ax.plot([h.best_cost for h in result.history], lw=1.4, label=label_)
        _j_scale(ax)
        ax.set_xlabel("iteration")
        ax.set_ylabel(label("best J", J_UNIT))
        ax.set_title("Fig. 6: convergence of the fitness J")
        ax.legend()
        fig.tight_layout()
    return save(fig, path)


def _j_scale(ax) -> None:
    """J on a log scale when it spans a decade or more, else linear (×10ⁿ on the axis)."""
    y = np.concatenate([np.asarray(ln.get_ydata(), float) for ln in ax.get_lines()] or [np.ones(1)])
    y = y[np.isfinite(y) & (y > 0)]
    if y.size and y.max() >= 10 * y.min():
        ax.set_yscale("log")
    else:
        ax.ticklabel_format(axis="y", style="sci", scilimits=(0, 0))


def plot_gains(result, path: str | Path, title: str = "") -> Path:
    """Every particle's k1, k2, k3 per iteration, and the best (paper Figs. 3-5)."""
    with styled():
        fig, axes = plt.subplots(3, 1, figsize=(WIDTH, 6.5), sharex=True)
        its = [h.iteration for h in result.history]
        for d, ax in enumerate(axes):
            xs = [np.full(len(h.positions), h.iteration) for h in result.history if h.positions.size]
            ys = [h.positions[:, d] for h in result.history if h.positions.size]
            if xs:
                ax.plot(np.concatenate(xs), np.concatenate(ys), ".", ms=2.5, color="0.65", label="particles")
            ax.plot(its, [h.best_position[d] for h in result.history], color=colour(1), lw=1.8,
                    label="global best")
            ax.set_ylabel(label(f"k{d + 1}", "1/s"))
        axes[0].set_title(title or "Figs. 3-5: gains over iterations")
        axes[0].legend(loc="upper right", ncol=2)
        axes[-1].set_xlabel("iteration")
        fig.align_ylabels(axes)
        fig.tight_layout()
    return save(fig, path)


def plot_convergence_spread(groups, path: str | Path) -> Path:
    """Best J per iteration, one colour per variant: the one run, or the mean over
    seeds with the min-max band (paper Fig. 6)."""
    return save(draw_convergence_spread(groups), path)


def draw_convergence_spread(groups):
    """The figure of :func:`plot_convergence_spread`."""
    with styled():
        fig, ax = plt.subplots(figsize=(WIDTH, 4.5))
        for i, (label_, results) in enumerate(groups):
            n = min(len(r.history) for r in results)
            j = np.array([[h.best_cost for h in r.history[:n]] for r in results])
            seeds = len(results)
            name = label_ if seeds == 1 else f"{label_} (mean of {seeds} seeds, band: min-max)"
            ax.plot(j.mean(0), lw=1.4, color=colour(i), label=name)
            if seeds > 1:
                ax.fill_between(range(n), j.min(0), j.max(0), color=colour(i), alpha=0.15, lw=0)
        _j_scale(ax)
        ax.set_xlabel("iteration")
        ax.set_ylabel(label("best J", J_UNIT))
        ax.set_title("Fig. 6: convergence of J" + (" over seeds" if any(len(r) > 1 for _, r in groups) else ""))
        ax.legend(fontsize=8)
        fig.tight_layout()
    return fig


#: Scenario kinds in the order the robustness figure groups them.
KIND_ORDER = ("nominal", "road", "drift", "noise", "other")
#: A gain set whose J stays within this factor of the baseline's on every scenario gets the % panel.
CLOSE_FACTOR = 2.0


def plot_robustness(table, path: str | Path, baseline: str | None = None) -> Path:
    """Per scenario, each gain set's J relative to ``baseline``'s (default: the
    first gain set), a ratio on a log scale, scenarios named and grouped by kind
    (:attr:`RobustnessTable.kinds`). Gain sets that stay within a factor
    :data:`CLOSE_FACTOR` of the baseline everywhere also get a panel of the
    difference in percent, with the count of scenarios each does better on. A
    diverged run is an ``x`` at the top of the ratio panel."""
    return save(draw_robustness(table, baseline)[0], path)


def draw_robustness(table, baseline: str | None = None):
    """(figure, ratio axes, percent axes or None, scenario order) of :func:`plot_robustness`."""
    labels = list(table.labels)
    base = labels.index(baseline) if baseline is not None else 0
    j = table.scores.costs
    names = list(table.scores.names)
    kinds = list(getattr(table, "kinds", ()) or ["other"] * len(names))
    order = sorted(range(len(names)), key=lambda s: (KIND_ORDER.index(kinds[s]) if kinds[s] in KIND_ORDER
                                                     else len(KIND_ORDER), s))
    jb = j[base, order]
    others = [p for p in range(len(labels)) if p != base]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = {p: j[p, order] / jb for p in others}
    close = [p for p in others if np.all(np.isfinite(ratio[p]))
             and np.all((ratio[p] <= CLOSE_FACTOR) & (ratio[p] >= 1 / CLOSE_FACTOR))]
    x = np.arange(len(order))
    with styled():
        rows = 2 if close else 1
        fig, axs = plt.subplots(rows, 1, figsize=(WIDTH, 6.2 if close else 4.4), sharex=True,
                                gridspec_kw={"height_ratios": [1.3, 1.0][:rows]}, squeeze=False)
        ax = axs[0, 0]
        ax.axhline(1.0, color=BLACK, lw=1.0, ls="--", label=f"{labels[base]} (baseline)")
        finite = np.concatenate([r[np.isfinite(r) & (r > 0)] for r in ratio.values()] or [np.ones(1)])
        top = finite.max() * 3 if finite.size else 10.0
        for p in others:
            r = ratio[p]
            ok = np.isfinite(r) & (r > 0)
            ax.semilogy(x[ok], r[ok], "o", ms=4, color=colour(p), label=labels[p])
            if (~ok).any():
                ax.semilogy(x[~ok], np.full((~ok).sum(), top), "x", ms=7, color=colour(p),
                            label=f"{labels[p]}: diverged ({(~ok).sum()})")
        ax.set_ylabel(label(f"J / J({labels[base]})", "1"))
        ax.set_title(f"J of each gain set relative to {labels[base]}'s, on {len(names)} scenarios", pad=16)
        ax.legend(loc="upper left", fontsize=8, ncol=2)
        pct = None
        if close:
            pct = axs[1, 0]
            width = 0.8 / len(close)
            for k, p in enumerate(close):
                d = (ratio[p] - 1.0) * 100.0
                better = int(np.sum(d < 0))
                pct.bar(x - 0.4 + width * (k + 0.5), d, width, color=colour(p),
                        label=f"{labels[p]}: lower J on {better} of {len(d)} scenarios, "
                              f"median {np.median(d):+.1f} %")
            pct.axhline(0.0, color=BLACK, lw=1.0)
            pct.set_ylabel(label(f"J vs {labels[base]}", "%"))
            pct.legend(loc="upper left", fontsize=8)
        _group_by_kind(axs[:, 0], [kinds[s] for s in order])
        bottom = axs[-1, 0]
        bottom.set_xticks(x)
        bottom.set_xticklabels([names[s] for s in order], rotation=90, fontsize=7 if len(order) > 30 else 8)
        bottom.set_xlim(-0.7, len(order) - 0.3)
        bottom.set_xlabel("scenario (grouped by kind)")
        for a in axs[:, 0]:
            a.grid(True, axis="x", alpha=0.0)
        fig.align_ylabels(axs[:, 0])
        fig.tight_layout()
    return fig, ax, pct, order


def _group_by_kind(axes, kinds: list[str]) -> None:
    """Separators between kinds and each kind's name above its group."""
    edges = [0] + [i for i in range(1, len(kinds)) if kinds[i] != kinds[i - 1]] + [len(kinds)]
    for ax in axes:
        for e in edges[1:-1]:
            ax.axvline(e - 0.5, color="0.5", lw=0.8)
    top = axes[0]
    for a, b in zip(edges, edges[1:]):
        top.text((a + b - 1) / 2, 1.0, f"{kinds[a]} ({b - a})", transform=top.get_xaxis_transform(),
                 ha="center", va="bottom", fontsize=8, color="0.25")
