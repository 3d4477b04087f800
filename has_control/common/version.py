"""The package's version: one home, setup.py's ``version`` (``package.xml`` repeats it).

Installed (pip or colcon), the distribution's metadata says it; run from a
source tree, setup.py is read. ``has_control.__version__`` and
``has-control --version`` both come from :func:`package_version`.
"""
from __future__ import annotations

import re
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


@lru_cache(maxsize=1)
def package_version() -> str:
    try:
        return version("has_control")
    except PackageNotFoundError:
        setup = Path(__file__).resolve().parent.parent.parent / "setup.py"
        m = re.search(r'version="([^"]+)"', setup.read_text()) if setup.is_file() else None
        return m.group(1) if m else "unknown"
