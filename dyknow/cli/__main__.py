"""``python -m dyknow.cli``: the ``dyknow`` command (:func:`dyknow.cli.main`)."""

from __future__ import annotations

from dyknow.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
