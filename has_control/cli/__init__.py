"""The command line: ``has-control`` and the demo."""
from has_control.common.interrupts import quiet_interrupts

with quiet_interrupts():      # the subcommands load the library (about a second): a Ctrl-C meanwhile is one line
    from has_control.cli.main import main  # noqa: F401
