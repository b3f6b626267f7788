"""Where the shipped specs live: next to the package in a checkout, or installed data files."""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["specs_dir"]


def specs_dir() -> Path:
    """The folder of shipped specs: ``$DYKNOW_SPECS``, the checkout's ``specs/``, or the installed copy."""
    env = os.environ.get("DYKNOW_SPECS")
    candidates = [Path(env)] if env else []
    candidates += [
        Path(__file__).resolve().parent.parent / "specs",
        Path(sys.prefix) / "share" / "dyknow" / "specs",
    ]
    for path in candidates:
        if (path / "generic.xml").is_file():
            return path
    raise FileNotFoundError(
        "cannot find dyknow's shipped specs (looked in " + ", ".join(str(p) for p in candidates) + "); set DYKNOW_SPECS"
    )
