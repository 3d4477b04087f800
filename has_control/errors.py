"""Errors the user can act on. Each carries one line naming the culprit."""


class HasControlError(Exception):
    """Base for errors reported as a single line and a non-zero exit."""


class ConfigError(HasControlError, ValueError):
    """A parameter file or parameter value is invalid (names file, key, value)."""
