"""What the loop needs of a logger: rclpy's ``RcutilsLogger`` calls, kept to
``info``/``warning``/``error`` with an optional ``throttle_duration_sec``.

:class:`ListLog` keeps the lines (tests, and a loop run without ROS)."""
from __future__ import annotations


class ListLog:
    """A logger that keeps (level, message) pairs; throttling is not applied."""

    def __init__(self):
        self.lines: list[tuple[str, str]] = []

    def info(self, message: str, **_) -> None:
        self.lines.append(("info", message))

    def warning(self, message: str, **_) -> None:
        self.lines.append(("warning", message))

    def error(self, message: str, **_) -> None:
        self.lines.append(("error", message))
