"""The tuned gains as a ``--params-file`` for the controller."""
from __future__ import annotations

from pathlib import Path

from has_control.common.files import write_atomic


def gains_params_yaml(gains, note: str = "") -> str:
    """A ``--params-file`` that sets ``gains.k1..k3`` [1/s] on every node that
    declares them (``/**``: the controller in any namespace), as rcl reads it."""
    k = [float(g) for g in gains]
    head = f"# {note}\n" if note else ""
    return (head + "/**:\n  ros__parameters:\n    gains:\n"
            + "".join(f"      k{i + 1}: {v!r}\n" for i, v in enumerate(k)))


def write_gains_params(path: str | Path, gains, note: str = "") -> Path:
    """Write :func:`gains_params_yaml` to ``path`` (written then renamed)."""
    return write_atomic(path, gains_params_yaml(gains, note))
