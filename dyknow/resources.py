"""The files shipped beside the package: the specs (in a checkout, or installed data files), and
the sources beside the modules that mypyc compiled."""

from __future__ import annotations

import ast
import os
import sys
from collections.abc import Iterable, MutableMapping
from pathlib import Path
from typing import Any

__all__ = ["restore_docstrings", "specs_dir"]


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


def restore_docstrings(namespace: MutableMapping[str, Any], names: Iterable[str]) -> None:
    """Give the classes among ``names`` in ``namespace`` (a package's ``globals()``, its
    ``__all__``) the docstrings that compiling with mypyc (see setup.py) took away, from the source
    beside the compiled module, so that ``help()`` still explains them. Compiled functions keep no
    docstring to give back (their ``__doc__`` cannot be set); the site's reference reads the source.
    """
    sources: dict[str, dict[str, str]] = {}
    for name in names:
        cls = namespace[name]
        if not isinstance(cls, type) or (cls.__doc__ or "").strip() not in ("", "mypyc filler docstring"):
            continue
        module = sys.modules[cls.__module__]
        if cls.__module__ not in sources:
            source = Path(str(module.__file__)).with_name(cls.__module__.rsplit(".", 1)[-1] + ".py")
            tree = ast.parse(source.read_text(encoding="utf-8")) if source.is_file() else ast.Module(body=[], type_ignores=[])
            sources[cls.__module__] = {node.name: ast.get_docstring(node) or "" for node in tree.body if isinstance(node, ast.ClassDef)}
        cls.__doc__ = sources[cls.__module__].get(cls.__name__) or cls.__doc__
