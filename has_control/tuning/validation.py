"""The validation of a tuning's best gains through the node graph, against the library.

Through the graph (the tuner node's lanes) the best gains' J equals the
library's J of the same gains on the tuner's model bit for bit when the lanes
run that model and miss no sample. So the graph's J is compared with the
library's: a relative difference beyond ``tolerance`` (default
:data:`VALIDATION_TOLERANCE`) means the graph is not what was tuned (a lane
with another model, missed samples), and the ``validation`` block of the
result says so (``agrees: false``), naming the lanes' parameters that differ
from the tuner's. ROS-free: the lanes' parameters arrive as plain dicts.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

from has_control.common.json_numbers import to_json

#: Relative difference between the graph's J and the library's J of the best gains above which the
#: validation disagrees (graph = library bit for bit when the lanes run the tuner's model and miss nothing).
VALIDATION_TOLERANCE = 1e-6


def relative_difference(graph: float, library: float) -> float:
    """|graph - library| / |library|; 0 when equal (both +inf included), +inf when the library's is 0 or not finite."""
    if graph == library:
        return 0.0
    if library == 0 or not math.isfinite(library):
        return math.inf
    return abs(graph - library) / abs(library)


def lane_differences(mine: Mapping[str, Any], lanes: list[dict]) -> list[str]:
    """Each lane parameter (``{"lane", "controller": {...}, "plant": {...}}``) whose value differs
    from the tuner's own ``mine`` (gains aside: they are the candidate's), one line each."""
    out = []
    for lane in lanes:
        for role in ("controller", "plant"):
            for key, value in (lane.get(role) or {}).items():
                if key in mine and not key.startswith("gains.") and _plain(value) != _plain(mine[key]):
                    out.append(f"{lane['lane']} {role}: {key} = {value!r} (the tuner's {mine[key]!r})")
    return out


def validation_block(score_json: dict, graph: float, library: float, differences: list[str],
                     tolerance: float = VALIDATION_TOLERANCE) -> dict:
    """The result's ``validation``: the graph run's score (``score_json``: J, e_max, ...),
    ``library_J``, ``relative_difference``, ``tolerance``, ``agrees`` and ``lane_differences``."""
    diff = relative_difference(graph, library)
    return {**score_json, "library_J": to_json(library), "relative_difference": to_json(diff),
            "tolerance": tolerance, "agrees": bool(diff <= tolerance), "lane_differences": list(differences)}


def validation_line(block: dict, gains) -> str:
    """One log line of a validation block (a warning when it disagrees)."""
    k = f"({gains[0]:.2f}, {gains[1]:.2f}, {gains[2]:.2f})"
    line = (f"validated k = {k} through the graph: J = {float(block['J']):.6e} (the library's J of these gains "
            f"{float(block['library_J']):.6e}, relative difference {float(block['relative_difference']):.3g})")
    if block["agrees"]:
        return line
    differ = block["lane_differences"]
    return (f"{line}: more than the tolerance {block['tolerance']:g}"
            + (f"; the lanes differ from the tuner's model: {'; '.join(differ[:5])}" if differ else ""))


def disagreement_status(gains, batch_j, block: dict) -> str:
    """The tuner's status after a session whose validation disagrees (never 'finished')."""
    return (f"disagrees: best k = {tuple(round(k, 2) for k in gains)}, batch J = {batch_j}, but the graph's "
            f"J = {block['J']} against the library's {block['library_J']} (relative difference "
            f"{float(block['relative_difference']):.3g} > tolerance {block['tolerance']:g}); see the lanes' "
            "parameters in the result")


def _plain(value):
    return list(value) if isinstance(value, (list, tuple)) else value
