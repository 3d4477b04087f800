"""``python -m has_control.cli``: the has-control command."""
import sys

from has_control.cli.main import main

sys.exit(main())
