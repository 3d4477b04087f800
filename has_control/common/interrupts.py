"""Signal policy shared by the command line and the nodes: Ctrl-C and SIGTERM
end a command with one line, ``has-control: interrupted``, and status 130."""
from __future__ import annotations

import os
import signal
import threading


def exit_quietly_on_interrupt(signum, frame):
    """Leave at once: an exception raised inside a C extension's import (numpy,
    numba) would be turned into an ImportError with a traceback."""
    os.write(2, b"has-control: interrupted\n")
    os._exit(130)


def raise_interrupt(signum, frame):
    """A SIGTERM handler: end as Ctrl-C does (``has_control.cli.main`` installs it)."""
    raise KeyboardInterrupt


class quiet_interrupts:
    """A context in which Ctrl-C or SIGTERM ends the process at once with one
    line and status 130 (as ``has_control.cli.main`` ends an interrupted
    command): for loading code (imports, numba's cache), where a
    KeyboardInterrupt would surface as an ImportError or an "Exception
    ignored" from a ctypes callback instead, and SIGTERM's default action
    would end the process silently. Each signal only while its handler is
    Python's default (main thread, nobody else's); restored on exit."""

    def __enter__(self):
        main = threading.current_thread() is threading.main_thread()
        defaults = {signal.SIGINT: (signal.default_int_handler,), signal.SIGTERM: (signal.SIG_DFL, raise_interrupt)}
        self.ours = {sig: signal.getsignal(sig) for sig, hs in defaults.items() if main and signal.getsignal(sig) in hs}
        for sig in self.ours:
            signal.signal(sig, exit_quietly_on_interrupt)
        return self

    def __exit__(self, *exc):
        for sig, handler in self.ours.items():
            signal.signal(sig, handler)
