"""One look for every figure: sizes, palette, labels with units, and saving.

Sizes are for a README read at 100 % zoom: figures 8 in wide at 100 dpi
(800 px, within GitHub's ~830 px column), text 10 pt (~14 px). Colours are
Okabe & Ito's colour-blind-safe palette (Color Universal Design, 2008),
black first for the reference. Every axis label names its unit:
:func:`label` writes ``quantity [unit]``.
"""
from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.backend_bases import FigureCanvasBase  # noqa: E402

from has_control.common.errors import HasControlError  # noqa: E402
from has_control.common.files import write_atomic  # noqa: E402

#: Okabe-Ito: black, orange, sky blue, bluish green, vermillion, blue, reddish purple, yellow.
BLACK, ORANGE, SKY, GREEN, VERMILLION, BLUE, PURPLE, YELLOW = (
    "#000000", "#E69F00", "#56B4E9", "#009E73", "#D55E00", "#0072B2", "#CC79A7", "#F0E442")
#: Colours of the runs / gain sets of one figure, in order (yellow last: weak on white).
PALETTE = (BLUE, VERMILLION, GREEN, ORANGE, PURPLE, SKY, BLACK, YELLOW)
#: Shade of the metric window (SPEC §6).
WINDOW_SHADE = dict(color="0.85", alpha=0.5, lw=0, zorder=0)
#: Figure width [in] and resolution [dpi]: 800 px wide.
WIDTH, DPI = 8.0, 100

RC = {
    "figure.dpi": DPI, "savefig.dpi": DPI, "figure.figsize": (WIDTH, 5.0),
    "font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10, "xtick.labelsize": 9, "ytick.labelsize": 9,
    "legend.fontsize": 9, "legend.framealpha": 0.9, "lines.linewidth": 1.3,
    "axes.prop_cycle": matplotlib.cycler(color=PALETTE), "axes.grid": True, "grid.alpha": 0.3,
    "grid.linewidth": 0.6, "axes.spines.top": False, "axes.spines.right": False,
    # text is text: a bag's name or a label with '$' is drawn as written, never parsed as mathtext
    "text.parse_math": False,
    "savefig.bbox": "tight", "savefig.pad_inches": 0.08, "axes.formatter.useoffset": False,
}


@contextmanager
def styled():
    """Draw inside this: the house rc settings, undone afterwards."""
    with plt.rc_context(RC):
        yield


def label(quantity: str, unit: str) -> str:
    """An axis label: ``quantity [unit]`` (unit ``1``: a dimensionless ratio)."""
    return f"{quantity} [{unit}]"


def colour(i: int) -> str:
    """The i-th run's colour."""
    return PALETTE[i % len(PALETTE)]


def figure_format(path: str | Path) -> str:
    """The format of a figure file, its suffix (none: png); one line naming
    ``path`` if matplotlib writes no such format."""
    fmt = Path(path).suffix[1:].lower() or "png"
    known = FigureCanvasBase.get_supported_filetypes()
    if fmt not in known:
        raise HasControlError(f"{path}: a figure cannot be written as '{fmt}' (one of {', '.join(sorted(known))})")
    return fmt


def save(fig, path: str | Path) -> Path:
    """Write the figure (then rename: never half a file) and close it."""
    try:
        fmt = figure_format(path)
        with styled():
            return write_atomic(path, lambda tmp: fig.savefig(tmp, format=fmt))
    finally:
        plt.close(fig)
