"""YAML as a parameter file needs it, hardened: floats as ROS reads them, no
aliases, bounded nesting, no key given twice; errors in one line naming the file."""
from __future__ import annotations

import re
from typing import Any, Mapping

import yaml

from has_control.common.errors import ConfigError

MAX_YAML_DEPTH = 32                 # nesting of mappings and lists in one document


class _Loader(yaml.SafeLoader):
    """SafeLoader that reads ``7.0e8`` and ``1e-3`` as floats, as ROS 2's
    parameter parser does (PyYAML's YAML 1.1 rules read them as strings),
    and refuses what a parameter file has no use for and an attacker does:
    aliases (self-reference, alias bombs), nesting deeper than
    :data:`MAX_YAML_DEPTH`, and a key given twice in one mapping."""

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(None, None, f"alias *{event.anchor}: aliases are not accepted",
                                              event.start_mark)
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise yaml.composer.ComposerError(None, None, f"nested deeper than {MAX_YAML_DEPTH} levels",
                                                  self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key, _ in node.value:
            if isinstance(key, yaml.ScalarNode):
                if key.value in seen:
                    raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key.value!r}",
                                                            key.start_mark)
                seen.add(key.value)
        return super().construct_mapping(node, deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def flatten(tree: Mapping[str, Any], prefix: str = "", where: str = "") -> dict[str, Any]:
    """``{'a': {'b': 1}}`` → ``{'a.b': 1}`` (the way rclpy names nested
    parameters). A name reached twice (``a.b`` given dotted and nested in
    ``a``) is refused naming ``where`` and the name: the later one would
    silently win."""
    flat: dict[str, Any] = {}
    _flatten_into(flat, tree, prefix, where)
    return flat


def _flatten_into(flat: dict[str, Any], tree: Mapping[str, Any], prefix: str, where: str) -> None:
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            _flatten_into(flat, value, name + ".", where)
        elif name in flat:
            raise ConfigError(f"{where + ': ' if where else ''}{name}: given twice (dotted and nested)")
        else:
            flat[name] = value


def load_yaml(text: str, where: str, error: type[Exception] = ConfigError, what: str = "not valid YAML") -> Any:
    """One YAML document under :class:`_Loader`'s rules; ``error`` naming
    ``where`` and the line if it is not valid."""
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark else ""
        problem = getattr(exc, "problem", None)
        why = f": {' '.join(str(problem).split())}" if problem else ""
        raise error(f"{where}: {what}{line}{why}") from None
    except ValueError as exc:                  # e.g. an integer of more digits than Python converts
        raise error(f"{where}: {what}: {' '.join(str(exc).split())[:120]}") from None
