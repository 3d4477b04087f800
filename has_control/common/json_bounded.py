"""JSON from a file someone may have edited: parsed with its nesting bounded.

Python's ``json`` recurses once per level: a document of 100 000 nested
brackets is a ``RecursionError``. :func:`loads_bounded` reads it as one line
naming where it came from, and refuses anything nested deeper than the
caller's limit (the project's records are a few levels deep).
"""
from __future__ import annotations

import json
from typing import Any

from has_control.common.errors import HasControlError

#: Nesting of objects and arrays in one record (the deepest the project writes is 4).
MAX_JSON_DEPTH = 16


def depth(value: Any) -> int:
    """Nesting of dicts and lists in ``value`` (a scalar: 0), without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            v = list(v.values())
        if isinstance(v, list):
            deepest = max(deepest, d)
            stack.extend((x, d + 1) for x in v if isinstance(x, (dict, list)))
    return deepest


def loads_bounded(text: str | bytes, where: str, error: type[HasControlError] = HasControlError,
                  limit: int = MAX_JSON_DEPTH) -> Any:
    """``json.loads(text)``, or one line naming ``where`` if it is not JSON or
    is nested deeper than ``limit`` objects and arrays."""
    try:
        value = json.loads(text)
    except RecursionError:
        raise error(f"{where}: JSON nested deeper than {limit} levels") from None
    except (ValueError, TypeError) as exc:
        raise error(f"{where}: not JSON ({' '.join(str(exc).split())[:80]})") from None
    if depth(value) > limit:
        raise error(f"{where}: JSON nested deeper than {limit} levels")
    return value
