"""One parameter table per component: each parameter's name, type, default,
unit, meaning, range, choices and whether it is read only at start-up.

A :class:`Param` is the one home of a parameter's facts. From it derive the
checks (:meth:`Param.check`: the type, with a whole number accepted for a
double, the range and the choices, in the one-line wording of a
:class:`~has_control.common.errors.ConfigError`), the nodes' ROS parameter
descriptors (:mod:`has_control.nodes.parameters`), each node's ``--help``
(:mod:`has_control.cli.node_help`) and the trailing comments of the shipped
``config/*.yaml`` (:func:`yaml_with_comments`; ``test/test_config.py`` keeps
them in step). The components' tables: the episode's configuration
(:data:`has_control.config.schema.CONFIG_TABLE`), the tuning settings
(:data:`has_control.tuning.parameters.TUNING_TABLE`) and each node's own
(``OWN_PARAMETERS`` of :mod:`~has_control.nodes.plant_node`,
:mod:`~has_control.nodes.controller_node`, :mod:`~has_control.nodes.tuner_node`).
"""
from __future__ import annotations

import dataclasses
import math
import re
from typing import Any, Callable, Iterable, Mapping

from has_control.common.errors import shown

#: The types a parameter may have (ROS parameter types).
TYPES = ("double", "int", "bool", "str", "double[]", "str[]")


@dataclasses.dataclass(frozen=True)
class Param:
    """A parameter. ``lower``/``upper``: its range (None: open), excluded when
    ``lower_open``/``upper_open``; for an array, each element's. ``length``:
    an array's element count (None: any). ``default`` None: the shipped
    config files give it. ``read_only``: read at start-up (or at ``~/start``)
    only. ``check_more(value)``: a further check, the reason or None.
    ``range_words``: the range in words where the bounds alone would not say
    it (a seed's ``[0, 2^63)``)."""

    name: str
    type: str
    default: Any = None
    unit: str = ""
    text: str = ""
    lower: float | None = None
    upper: float | None = None
    lower_open: bool = False
    upper_open: bool = False
    choices: tuple[str, ...] = ()
    read_only: bool = False
    length: int | None = None
    check_more: Callable[[Any], str | None] | None = None
    range_words: str = ""

    def __post_init__(self):
        assert self.type in TYPES, self.type

    # --- what it takes, in words -------------------------------------------------
    @property
    def is_array(self) -> bool:
        return self.type.endswith("[]")

    def range_text(self) -> str:
        """The range in words ('> 0 and <= 1e+06', 'in [0, 99]'); '' for none."""
        if self.range_words:
            return self.range_words
        lo, hi = self.lower, self.upper
        if self.type == "int" and lo is not None and hi is not None:
            return f"in [{lo:g}, {hi:g}]"
        parts = []
        if lo is not None:
            parts.append(f"{'>' if self.lower_open else '>='} {lo:g}")
        if hi is not None:
            parts.append(f"{'<' if self.upper_open else '<='} {hi:g}")
        return " and ".join(parts)

    def constraint(self) -> str:
        """What the value must be, for help and descriptors ('one of: a, b', '> 0', ...)."""
        if self.choices:
            return f"one of: {', '.join(self.choices)}"
        rng = self.range_text()
        if not rng:
            return ""
        return f"each {rng}" if self.is_array else rng

    def comment(self) -> str:
        """The meaning and unit, as the YAML files' trailing comment says it."""
        return f"{self.text} [{self.unit}]" if self.unit else self.text

    def help_text(self) -> str:
        """One line for ``--help``: meaning [unit] (range; read at start-up)."""
        extra = [c for c in (self.constraint(),) if c]
        if self.read_only:
            extra.append("read at start-up")
        return self.comment() + (f" ({'; '.join(extra)})" if extra else "")

    # --- the check -----------------------------------------------------------------
    def coerce(self, value: Any) -> Any:
        """``value`` as this parameter's type where that loses nothing (a whole
        number for a double, a list of them for a double array, ROS arrays as
        lists); anything else unchanged, for :meth:`check` to refuse."""
        if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
            value = value.tolist()
        if self.type == "double" and isinstance(value, int) and not isinstance(value, bool):
            try:
                return float(value)
            except OverflowError:
                return value
        if self.type == "double[]" and isinstance(value, (list, tuple)):
            return [float(v) if isinstance(v, int) and not isinstance(v, bool) and abs(v) < 2 ** 1023 else v
                    for v in value]
        if self.type == "str[]" and isinstance(value, tuple):
            return list(value)
        return value

    def check(self, value: Any) -> str | None:
        """Why ``value`` (after :meth:`coerce`) is not valid, or None."""
        value = self.coerce(value)
        t = self.type
        if t == "bool":
            return None if isinstance(value, bool) else "expected true or false"
        if t == "str":
            if not isinstance(value, str) and not self.choices:
                return "expected a string"
            if self.choices and (not isinstance(value, str) or value not in self.choices):
                return f"expected one of {', '.join(sorted(self.choices))}"
        elif t == "int":
            if isinstance(value, bool) or not isinstance(value, int):
                return f"expected a whole number{' ' + self.range_text() if self.range_words else ''}"
            why = self._out_of_range(value)
            if why:
                return why
        elif t == "double":
            why = _number(value) or self._out_of_range(value)
            if why:
                return why
        elif t == "double[]" or t == "str[]":
            if not isinstance(value, (list, tuple)) or (self.length is not None and len(value) != self.length):
                n = {2: "two", 3: "three"}.get(self.length, str(self.length)) if self.length else ""
                what = "numbers" if t == "double[]" else "strings"
                return f"expected a list of {n + ' ' if n else ''}{what}"
            for v in value:
                why = (_number(v) or self._out_of_range(v)) if t == "double[]" else (
                    None if isinstance(v, str) else "expected a list of strings")
                if why:
                    return why
        return self.check_more(value) if self.check_more is not None else None

    def _out_of_range(self, v: float) -> str | None:
        lo, hi = self.lower, self.upper
        if (lo is not None and (v < lo or (self.lower_open and v == lo))) or (
                hi is not None and (v > hi or (self.upper_open and v == hi))):
            rng = self.range_text()
            if self.type == "int":
                return f"{'expected' if self.range_words else 'must be'} a whole number {rng}"
            return f"must be {rng}"
        return None


def _number(v: Any) -> str | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return "expected a number"
    try:
        v = float(v)
    except OverflowError:
        return "must be finite"
    return None if math.isfinite(v) else "must be finite"


def table(params: Iterable[Param]) -> dict[str, Param]:
    """A component's table by name (a name twice is a bug)."""
    out: dict[str, Param] = {}
    for p in params:
        assert p.name not in out, p.name
        out[p.name] = p
    return out


def refusal(params: Mapping[str, Param], name: str, value: Any) -> str | None:
    """``name = value: why`` if ``value`` is not valid for ``params[name]``, else None (unknown names pass)."""
    p = params.get(name)
    why = p.check(value) if p is not None else None
    return None if why is None else f"{name} = {_shown(value)}: {why}"


def _shown(value: Any) -> str:
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        value = value.tolist()
    return shown(value)


# --- the YAML files' comments -------------------------------------------------------
_VALUE_LINE = re.compile(r"^(?P<indent>\s*)(?P<key>[A-Za-z_]\w*):(?P<gap>\s*)(?P<value>[^#\s][^#]*?)"
                         r"(?P<pad>\s*)(?P<comment>#.*)?$")


def yaml_with_comments(text: str, params: Mapping[str, Param], root: str = "") -> str:
    """``text`` (a ``ros__parameters`` file) with each value line's trailing
    comment made the table's :meth:`Param.comment` (keys without one are
    left as they are; lines without a value too). The shipped files are
    kept in this form, so the table is the one source of their comments."""
    out = []
    stack: list[tuple[int, str]] = []
    column = 0                                  # where the last trailing comment began: new ones align to it
    for line in text.splitlines():
        m = _VALUE_LINE.match(line)
        bare = re.match(r"^(\s*)([A-Za-z_/*][\w/*]*):\s*(#.*)?$", line)
        if bare:
            if bare.group(3):
                column = line.index("#")
            indent = len(bare.group(1))
            while stack and stack[-1][0] >= indent:
                stack.pop()
            stack.append((indent, bare.group(2)))
            out.append(line)
            continue
        if not m:
            out.append(line)
            continue
        indent = len(m.group("indent"))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        dotted = ".".join([k for _, k in stack if k not in ("/**", "ros__parameters") and "/" not in k]
                          + [m.group("key")])
        p = params.get(root + dotted)
        if p is None or not p.comment():
            out.append(line)
            continue
        head = f"{m.group('indent')}{m.group('key')}:{m.group('gap')}{m.group('value')}"
        pad = m.group("pad") if m.group("comment") else " " * max(1, column - len(head))
        column = len(head) + len(pad)
        out.append(f"{head}{pad}# {p.comment()}")
    return "\n".join(out) + ("\n" if text.endswith("\n") else "")
