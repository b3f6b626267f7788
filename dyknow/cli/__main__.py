"""``python -m dyknow.cli``: the ``dyknow`` command (:func:`dyknow.cli.run`)."""

from __future__ import annotations

from dyknow.cli import run

if __name__ == "__main__":
    run()
