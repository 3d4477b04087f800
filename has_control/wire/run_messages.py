"""A run from the messages its loop exchanged: what a recorder took, as one
:class:`~has_control.core.run.Run` (the node stack's run and score come from here).

The messages (or chunks of them joined, as a recorder keeps them) are the
loop's own layouts (:mod:`has_control.wire.topics`), refused otherwise: the
plant's states (its true states where it publishes sensor readings on
``state``), the commands, the controller's ``controller_state`` and the
plant's ``plant/missed`` reports. Each goes to its sample: a state or a
command by its stamp, an array by its leading t. Row i is sample i:

* t = i·Δt [s]; x1d the reference at t (:func:`~has_control.core.reference.reference_series`);
* y [m], ẏ [m/s], P1, P2 [Pa] from the state; e1 = x1d − y [m];
* u [m], the command the plant ran with: the one reported missed (held, or 0 on
  the fail-safe) where there is one, else the controller's command;
* e2, e3, â1, â2 from ``controller_state`` where the controller answered; NaN elsewhere.

The run ends at the last sample that has a state and a command the plant
ran with (a command, or a missed report).
"""
from __future__ import annotations

import numpy as np

from has_control.core.reference import reference_series
from has_control.core.run import Run
from has_control.wire.codec import Layout
from has_control.wire.topics import (COMMAND_LAYOUT, CONTROLLER_STATE_COLUMNS, CONTROLLER_STATE_LAYOUT, MISSED_COLUMNS,
                                     MISSED_LAYOUT, STATE_LAYOUT)

#: Where y, ẏ, P1, P2 sit among a state's nine values (position, velocity, effort of three joints).
_Y, _YDOT, _P1, _P2 = 0, 3, 7, 8


def _matrix(messages: list[bytes], layout: Layout, what: str) -> np.ndarray:
    """The messages (or chunks of messages joined) as a (n, size) byte matrix;
    refused if one is of another layout (its size or its fixed bytes)."""
    size = layout.size
    raw = b"".join(messages)
    matrix = np.frombuffer(raw, dtype=np.uint8).reshape(-1, size) if len(raw) % size == 0 else None
    if matrix is None or not (matrix[:, layout.fixed] == layout.template[layout.fixed]).all():
        raise ValueError(f"{what}: a message of another layout than the loop's ({size} bytes each)")
    return matrix


def _values(matrix: np.ndarray, layout: Layout) -> np.ndarray:
    """(n, values) float64 of a byte matrix of ``layout``."""
    cols = [matrix[:, int(off):int(off) + 8].copy().view("<f8").ravel() for off in layout.values]
    return np.column_stack(cols) if cols else np.zeros((len(matrix), 0))


def _stamp_samples(matrix: np.ndarray, step_ns: int) -> np.ndarray:
    """The sample of each stamped message (stamp / Δt)."""
    sec = matrix[:, 4:8].copy().view("<i4").ravel().astype(np.int64)
    nsec = matrix[:, 8:12].copy().view("<u4").ravel().astype(np.int64)
    return (sec * 1_000_000_000 + nsec) // step_ns


def _time_samples(t: np.ndarray, step: float) -> np.ndarray:
    return np.rint(t / step).astype(np.int64)


def _place(n: int, rows: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` at ``rows`` of an n-row column (the last message of a sample wins), NaN elsewhere."""
    out = np.full(n, np.nan)
    keep = (rows >= 0) & (rows < n)
    out[rows[keep]] = values[keep]
    return out


def run_of_messages(states: list[bytes], commands: list[bytes], internals: list[bytes], missed: list[bytes],
                    step: float, step_ns: int, rp: np.ndarray) -> Run:
    """The run the messages tell (see the module docstring): Δt ``step`` [s]
    (``step_ns`` [ns]), the reference array ``rp`` (:func:`~has_control.core.reference.reference_array`)."""
    sm = _matrix(states, STATE_LAYOUT, "state")
    cm = _matrix(commands, COMMAND_LAYOUT, "command")
    s_at, x = _stamp_samples(sm, step_ns), _values(sm, STATE_LAYOUT)
    c_at, cu = _stamp_samples(cm, step_ns), _values(cm, COMMAND_LAYOUT)[:, 0]
    iv = _values(_matrix(internals, CONTROLLER_STATE_LAYOUT, "controller_state"), CONTROLLER_STATE_LAYOUT)
    mv = _values(_matrix(missed, MISSED_LAYOUT, "plant/missed"), MISSED_LAYOUT)
    i_at = _time_samples(iv[:, 0], step)
    m_at = _time_samples(mv[:, MISSED_COLUMNS.index("t")], step)
    ran = np.union1d(c_at, m_at)
    both = np.intersect1d(s_at, ran)
    n = int(both[-1]) + 1 if both.size else 0
    u = _place(n, c_at, cu)
    ran_missed = (m_at >= 0) & (m_at < n)
    u[m_at[ran_missed]] = mv[ran_missed, MISSED_COLUMNS.index("u")]
    t = np.arange(n) * step
    c = CONTROLLER_STATE_COLUMNS.index
    inner = {k: _place(n, i_at, iv[:, c(k)]) for k in ("e2", "e3", "a1_hat", "a2_hat")}
    return Run.of(t, reference_series(rp, t)[:, 0], *(_place(n, s_at, x[:, k]) for k in (_Y, _YDOT, _P1, _P2)), u,
                  **inner)
