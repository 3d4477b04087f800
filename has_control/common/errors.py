"""Errors the user can act on. Each carries one line naming the culprit."""


def shown(value, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters, for an error line."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 1] + "…"


class HasControlError(Exception):
    """Base for errors reported as a single line and a non-zero exit."""


class ConfigError(HasControlError, ValueError):
    """A parameter file or parameter value is invalid (names file, key, value)."""
