"""One run, or several overlaid, as one figure a control engineer reads at a glance.

Panels over a shared time axis [s], top to bottom:

* position: the reference x1d and each run's y [mm];
* tracking error: |e1| [µm] on a log scale, so a tuned controller's
  micrometres and the start-up transient's millimetres both show; the metric
  window of SPEC §6 shaded, each run's e_max, e_μ, e_σ written in;
* valve command u [mm], with ± the valve's travel limit when the plant had
  one, and the samples a realtime bag holds no command for;
* chamber pressures P1 (solid) and P2 (dashed) [bar];
* the adaptive estimates â1 [N·s/m] and â2 [10⁻¹² m³/(s·Pa)] between their
  projection bounds (dotted);
* the gains in force k1, k2, k3 [1/s] (a tuner session may change them mid-run).

A run comes from an in-process :class:`~has_control.core.episode.Trace`
(:func:`view_of_trace`) or a bag (:func:`view_of_series` of
:func:`~has_control.bag.series.run_series`); :func:`draw` returns the figure
and its axes by name (tests read the plotted data back), :func:`plot_runs`
writes it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import matplotlib.pyplot as plt
from matplotlib.transforms import blended_transform_factory

from has_control.bag.series import RunSeries
from has_control.common.errors import HasControlError
from has_control.core.cost import score_arrays
from has_control.core.params import Config
from has_control.core.run import Run
from has_control.plots.style import BLACK, WIDTH, WINDOW_SHADE, colour, label, save, styled

MM, UM, BAR, A2_UNIT = 1e3, 1e6, 1e-5, 1e12          # m -> mm, m -> µm, Pa -> bar, â2 -> 10⁻¹² m³/(s·Pa)
#: Panels, top to bottom, and their relative heights.
PANELS = (("position", 1.0), ("error", 1.6), ("valve", 1.0), ("pressure", 1.0), ("a1", 0.8), ("a2", 0.8),
          ("gains", 0.8))
#: Height of one line of text in the error panel [fraction of the panel].
TEXT_ROW = 0.085
#: Lines longer than this are rasterised in PDF and SVG (the data stays on the Axes).
RASTER_POINTS = 5000


@dataclass(frozen=True)
class RunView:
    """What the run figure draws of one run: its :class:`~has_control.core.run.Run`
    (series on a time grid [s], SI units) and what the figure writes beside it."""

    label: str
    run: Run
    gains_t: np.ndarray                        # [s] when each gain set took effect
    gains: np.ndarray                          # (m, 3) [1/s]
    window: tuple[float, float] | None         # metric window [s] (SPEC §6)
    metrics: tuple[float, float, float] | None  # e_max, e_μ, e_σ of |e1| [m]
    metrics_note: str                          # "" (the run's SPEC §6 score) or how they were taken
    valve_limit: float                         # spool travel [m]; 0: none
    a_lower: tuple[float, float]
    a_upper: tuple[float, float]
    missed_t: np.ndarray                       # samples [s] with a state but no command recorded
    late_t: np.ndarray | None = None           # samples [s] a realtime plant ran without their command (recorded)
    failsafe_t: np.ndarray | None = None       # of those, the samples [s] on the fail-safe (valve centred)

    t = property(lambda self: self.run.t)
    x1d = property(lambda self: self.run.x1d)
    y = property(lambda self: self.run.y)
    u = property(lambda self: self.run.u)
    p1 = property(lambda self: self.run.p1)
    p2 = property(lambda self: self.run.p2)
    a1_hat = property(lambda self: self.run.a1_hat)
    a2_hat = property(lambda self: self.run.a2_hat)
    e1 = property(lambda self: self.run.e1)


def gains_text(k) -> str:
    """``k = (150, 158, 162)``: gains to the nearest 0.01 1/s, trailing zeros dropped."""
    return "k = (" + ", ".join(f"{round(float(v), 2):g}" for v in k) + ")"


def _window(cfg: Config) -> tuple[float, float] | None:
    ep = cfg.episode
    lo, hi = ep.window()
    return (lo * ep.step, hi * ep.step) if hi >= lo else None


def view_of_trace(trace, cfg: Config, name: str | None = None) -> RunView:
    """A simulated run (:class:`~has_control.core.episode.Trace`) under ``cfg``: its metrics are its score's."""
    s = trace.score
    g = trace.gains.as_tuple()
    return RunView(name or gains_text(g), trace, np.zeros(1), np.array([g]), _window(cfg),
                   None if s.diverged else (s.e_max, s.e_mu, s.e_sigma), "diverged" if s.diverged else "",
                   cfg.plant.valve_limit, cfg.adaptation.lower, cfg.adaptation.upper, np.zeros(0))


def view_of_series(run: RunSeries, name: str | None = None) -> RunView:
    """A recorded run. A complete run's metrics are ``has-control score``'s (SPEC §6,
    the same arithmetic); a partial one's are taken over the window's recorded samples."""
    cfg, ep = run.cfg, run.cfg.episode
    metrics, note = _series_metrics(run)
    missed = run.missing.get("command", np.zeros(0, np.int64))
    late = None if run.missed is None else run.missed * ep.step
    failsafe = None if run.failsafe is None else run.failsafe * ep.step
    return RunView(name or run.name, run, run.gains_t, run.gains, _window(cfg), metrics, note, cfg.plant.valve_limit,
                   cfg.adaptation.lower, cfg.adaptation.upper, missed * ep.step, late, failsafe)


def _series_metrics(run: RunSeries) -> tuple[tuple[float, float, float] | None, str]:
    """e_max, e_μ, e_σ of |e1| over the metric window (they need e1 only, not u):
    SPEC §6's arithmetic when e1 is whole, else over the window's recorded samples."""
    ep = run.cfg.episode
    n = ep.samples
    e1 = run.e1
    if len(e1) >= n and np.all(np.isfinite(e1[:n])):
        if np.any(np.abs(run.y[:n]) > ep.y_limit):
            return None, "diverged"
        s = score_arrays(e1[:n], np.nan_to_num(run.u[:n]), ep.as_array())   # J is not shown: u's gaps do not matter
        return (s.e_max, s.e_mu, s.e_sigma), ""
    lo, hi = ep.window()
    w = np.abs(e1[lo:hi + 1])
    w = w[np.isfinite(w)]
    if not w.size:
        return None, "no sample in the window"
    return (float(w.max()), float(w.mean()), float(w.std())), f"over {w.size} recorded samples"


def crop(view: RunView, start: float, end: float) -> RunView:
    """``view`` between ``start`` and ``end`` [s]; one line if it has no sample there."""
    keep = (view.t >= start) & (view.t <= end)
    if not keep.any():
        raise HasControlError(f"--window {start:g} {end:g}: {view.label} has no sample in it "
                              f"(recorded {view.t[0]:g} .. {view.t[-1]:g} s)")
    cut = {"run": Run(view.run.data[keep])}
    for k in ("missed_t", "late_t", "failsafe_t"):
        x = getattr(view, k)
        cut[k] = None if x is None else x[(x >= start) & (x <= end)]
    return replace(view, **cut)


@dataclass
class RunFigure:
    """The figure and its axes by panel name (see :data:`PANELS`)."""

    fig: object
    axes: dict
    views: tuple[RunView, ...]


def draw(views: Sequence[RunView], title: str | None = None) -> RunFigure:
    """The run figure of ``views`` (overlaid, one colour each)."""
    views = tuple(views)
    with styled():
        fig, axs = plt.subplots(len(PANELS), 1, sharex=True, figsize=(WIDTH, 12.0),
                                gridspec_kw={"height_ratios": [h for _, h in PANELS]})
        axes = {name: ax for (name, _), ax in zip(PANELS, axs)}
        for name, ax in axes.items():
            ax.set_label(name)
        _position(axes["position"], views)
        _error(axes["error"], views)
        _valve(axes["valve"], views)
        _pressure(axes["pressure"], views)
        _estimates(axes["a1"], axes["a2"], views)
        _gains(axes["gains"], views)
        axes["gains"].set_xlabel(label("time t", "s"))
        t0 = min(float(v.t[0]) for v in views)
        t1 = max(float(v.t[-1]) for v in views)
        axes["gains"].set_xlim(t0, t1 if t1 > t0 else t0 + 1e-3)
        for ax in axs:
            for line in ax.get_lines():
                if len(line.get_xdata()) > RASTER_POINTS:
                    line.set_rasterized(True)
        fig.suptitle(title or ("Run " + views[0].label if len(views) == 1 else "Runs compared"), y=0.995)
        fig.align_ylabels(axs)
        fig.tight_layout(h_pad=0.4)
    return RunFigure(fig, axes, views)


def plot_runs(views: Sequence[RunView], path: str | Path, title: str | None = None) -> Path:
    """Draw ``views`` and write the figure to ``path`` (its suffix: the format)."""
    return save(draw(views, title).fig, path)


def _position(ax, views) -> None:
    ax.plot(views[0].t, views[0].x1d * MM, "--", color=BLACK, lw=1.0, label="x1d (reference)")
    for i, v in enumerate(views):
        ax.plot(v.t, v.y * MM, color=colour(i), lw=1.1, label=f"y, {v.label}")
    ax.set_ylabel(label("position", "mm"))
    short = max(len(v.label) for v in views) <= 28
    ax.legend(loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=min(len(views) + 1, 3) if short else 1,
              fontsize=8, frameon=False, borderaxespad=0.1)


def _error(ax, views) -> None:
    """|e1| [µm], log scale; the metric window; e_max, e_μ, e_σ per run."""
    w = views[0].window
    t0, t1 = min(float(v.t[0]) for v in views), max(float(v.t[-1]) for v in views)
    if w is not None and (w[1] < t0 or w[0] > t1):
        w = None                               # the plotted time holds none of it
    if w is not None:
        ax.axvspan(w[0], w[1], **WINDOW_SHADE, label=f"metric window {w[0]:.3g} .. {w[1]:.3g} s")
    visible, inside = [], []
    for i, v in enumerate(views):
        e = np.abs(v.e1) * UM
        ax.plot(v.t, e, color=colour(i), lw=0.9, label=f"|e1|, {v.label}")
        ok = np.isfinite(e) & (e > 0)
        visible.append(e[ok])
        if v.window is not None:
            inside.append(e[ok & (v.t >= v.window[0]) & (v.t <= v.window[1])])
    ax.set_yscale("log")
    allv = np.concatenate(visible) if visible else np.zeros(0)
    win = np.concatenate(inside) if inside else np.zeros(0)
    base = win if win.size else allv
    if base.size:
        low = 0.3 * float(np.percentile(base, 0.5))
        high = 2.0 * float(allv.max())
        if high > low > 0:                     # head room for the metrics' lines: the top TEXT_ROW per run
            decades = math.log10(high / low)
            top = 0.04 + TEXT_ROW * len(views)
            ax.set_ylim(low, high * 10 ** (decades * top / (1.0 - top)))
    ax.set_ylabel(label("|e1|", "µm"))
    lines = []
    for i, v in enumerate(views):
        if v.metrics is None:
            text = f"{v.label}: {v.metrics_note or 'no metrics'}"
        else:
            a, b, c = (x * UM for x in v.metrics)
            text = f"e_max {a:.3g}, e_μ {b:.3g}, e_σ {c:.3g} µm" + (f" ({v.metrics_note})" if v.metrics_note else "")
            text = f"{v.label}: {text}" if len(views) > 1 else text
        lines.append((text, colour(i)))
    for k, (text, col) in enumerate(lines):
        ax.text(0.99, 0.97 - TEXT_ROW * k, text, transform=ax.transAxes, ha="right", va="top", fontsize=8.5,
                color=col, bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))
    if w is not None:
        ax.legend(handles=[ax.patches[0]], loc="lower right", fontsize=8)


def _valve(ax, views) -> None:
    """u [mm]; scaled to the metric window (and the valve limit), so a start-up
    spike does not flatten the rest: what lies off the scale is said."""
    for i, v in enumerate(views):
        ax.plot(v.t, v.u * MM, color=colour(i), lw=0.9)
    limits = sorted({v.valve_limit for v in views if v.valve_limit > 0})
    for lim in limits:
        for sign in (1, -1):
            ax.axhline(sign * lim * MM, color="0.4", ls=":", lw=1.0,
                       label=f"valve limit ±{lim * MM:g} mm" if sign > 0 else None)
    marked = _mark_misses(ax, views)
    _scale_to_window(ax, views, [v.u * MM for v in views], [x * MM for lim in limits for x in (lim, -lim)], "mm")
    ax.set_ylabel(label("valve u", "mm"))
    if limits or marked:
        ax.legend(loc="upper right", fontsize=8)


def _mark_misses(ax, views) -> bool:
    """Ticks along the bottom of the valve panel: the samples a realtime plant
    ran without their command (as its bag records them) and those on the
    fail-safe; where the bag does not record them, the samples it holds no command for."""
    rug = blended_transform_factory(ax.transData, ax.transAxes)
    marked = False
    for i, v in enumerate(views):
        if v.late_t is not None:
            marks = [(v.late_t, 0.04, "|", f"missed: ran on the held command ({_samples(len(v.late_t))})"),
                     (v.failsafe_t, 0.10, "v", f"fail-safe: valve centred ({_samples(len(v.failsafe_t))})")]
        else:
            marks = [(v.missed_t, 0.04, "|", f"no command recorded ({_samples(len(v.missed_t))})")]
        for x, y, marker, text in marks:
            if len(x):
                ax.plot(x, np.full(len(x), y), marker, ms=9 if marker == "|" else 5, mew=1.5, color=colour(i),
                        transform=rug, label=text, ls="none")
                marked = True
    return marked


def _scale_to_window(ax, views, values, also, unit: str) -> None:
    """y limits that hold ``values`` inside the metric window and ``also``,
    with a note if the values outside it go off that scale."""
    inside, whole = [], []
    for v, x in zip(views, values):
        ok = np.isfinite(x)
        whole.append(x[ok])
        if v.window is not None:
            inside.append(x[ok & (v.t >= v.window[0]) & (v.t <= v.window[1])])
    inside = np.concatenate(inside) if inside else np.zeros(0)
    whole = np.concatenate(whole) if whole else np.zeros(0)
    if not inside.size or not whole.size:
        return
    lo, hi = min(inside.min(), *also) if also else inside.min(), max(inside.max(), *also) if also else inside.max()
    pad = 0.15 * (hi - lo) if hi > lo else max(abs(hi), 1e-9) * 0.1
    lo, hi = lo - pad, hi + pad
    if whole.min() < lo or whole.max() > hi:
        ax.set_ylim(lo, hi)
        ax.text(0.01, 0.95, f"off scale outside the window: {whole.min():.3g} .. {whole.max():.3g} {unit}",
                transform=ax.transAxes, fontsize=8, va="top", color="0.3",
                bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8))


def _samples(n: int) -> str:
    return f"{n} sample{'s' if n != 1 else ''}"


def _pressure(ax, views) -> None:
    for i, v in enumerate(views):
        ax.plot(v.t, v.p1 * BAR, color=colour(i), lw=1.0, label="P1" if i == 0 else None)
        ax.plot(v.t, v.p2 * BAR, color=colour(i), lw=1.0, ls="--", label="P2" if i == 0 else None)
    ax.set_ylabel(label("pressure", "bar"))
    ax.legend(loc="upper right", ncol=2, fontsize=8)


def _estimates(ax1, ax2, views) -> None:
    for ax, k, key, scale, name, unit in ((ax1, 0, "a1_hat", 1.0, "â1", "N·s/m"),
                                          (ax2, 1, "a2_hat", A2_UNIT, "â2", "10⁻¹² m³/(s·Pa)")):
        for i, v in enumerate(views):
            ax.plot(v.t, getattr(v, key) * scale, color=colour(i), lw=1.0)
        bounds = sorted({(v.a_lower[k], v.a_upper[k]) for v in views})
        for lo, hi in bounds:
            for b in (lo, hi):
                ax.axhline(b * scale, color="0.4", ls=":", lw=1.0)
        lo = min(b[0] for b in bounds) * scale
        hi = max(b[1] for b in bounds) * scale
        pad = 0.08 * (hi - lo) if hi > lo else abs(hi) * 0.1 + 1e-12
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_ylabel(label(name, unit))
    ax1.text(0.01, 0.9, "dotted: projection bounds", transform=ax1.transAxes, fontsize=8, va="top",
             color="0.3")


def _gains(ax, views) -> None:
    t_end = max(float(v.t[-1]) for v in views)
    for i, v in enumerate(views):
        if not len(v.gains_t):
            continue
        t = np.append(v.gains_t, max(t_end, float(v.gains_t[-1])))
        for d, ls in enumerate(("-", "--", ":")):
            k = np.append(v.gains[:, d], v.gains[-1, d])
            ax.step(t, k, where="post", color=colour(i), ls=ls, lw=1.2,
                    label=f"k{d + 1}" if i == 0 else None)
    ax.set_ylabel(label("gains", "1/s"))
    if ax.get_lines():
        ax.legend(loc="upper right", ncol=3, fontsize=8)
        lo, hi = ax.get_ylim()
        if math.isclose(lo, hi):
            ax.set_ylim(lo - 1, hi + 1)
