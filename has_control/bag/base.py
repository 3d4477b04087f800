"""What the bag modules share: the error, warnings and our custom-data key."""
from __future__ import annotations

import sys
import warnings
from contextlib import contextmanager
from pathlib import Path

from has_control.common.errors import HasControlError

PARAMETERS_KEY = "has_control/parameters"


class BagError(HasControlError):
    """A bag that cannot be read or lacks what we need (one line naming the file)."""


def warn(message: str) -> None:
    print(f"has-control: warning: {message}", file=sys.stderr)


@contextmanager
def warnings_as_lines(on_warning=None):
    """Inside (or on a function, as a decorator): a Python warning raised by a
    library (numpy's RuntimeWarning on an overflow, matplotlib's UserWarning)
    is one line ``has-control: warning: Category: message (file:line)``, once
    per message, never the warnings module's two-line source echo."""
    seen: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None):
        text = f"{category.__name__}: {str(message).splitlines()[0] if str(message) else ''}"
        if text not in seen:
            seen.add(text)
            (on_warning or warn)(f"{text} ({Path(str(filename)).name}:{lineno})")

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield
