"""What the bag modules share: the error, warnings and our custom-data key."""
from __future__ import annotations

import sys

from has_control.common.errors import HasControlError

PARAMETERS_KEY = "has_control/parameters"


class BagError(HasControlError):
    """A bag that cannot be read or lacks what we need (one line naming the file)."""


def warn(message: str) -> None:
    print(f"has-control: warning: {message}", file=sys.stderr)
