"""Floats in JSON: JSON has no infinity or NaN, so they travel as strings.

``to_json`` writes +inf, -inf and NaN as "inf", "-inf" and "nan" (what
``has-control ... --json`` prints); ``float()`` reads them back.
"""
from __future__ import annotations

import math


def to_json(x) -> float | str:
    """A float (or NumPy scalar) as JSON: itself when finite, else "inf", "-inf" or "nan"."""
    x = float(x)
    if math.isfinite(x):
        return x
    if math.isnan(x):
        return "nan"
    return "inf" if x > 0 else "-inf"


def list_to_json(values) -> list:
    return [to_json(v) for v in values]
