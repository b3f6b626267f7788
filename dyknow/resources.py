"""The files shipped beside the package: the specs (in a checkout, or installed data files), and
the sources beside the modules that mypyc compiled.

On the command line the shipped files have names that work from any folder (:func:`shipped_path`):
``@shipped`` is the folder of shipped specs and ontology (``--specs @shipped``, ``--ontology
@shipped/dyknow.ttl``), ``@testing`` the folder of :mod:`dyknow.testing`'s scenario specs
(``@testing/scenario-station.xml``), ``@pipeline`` the pipeline robot's managing spec and mode
file (:mod:`dyknow.demo.pipeline`: ``@pipeline/pipeline.xml``); ``dyknow paths`` prints where they are.
"""

from __future__ import annotations

import ast
import os
import sys
from collections.abc import Iterable, MutableMapping
from pathlib import Path
from typing import Any

__all__ = ["SHIPPED_FILES", "SHIPPED_NAMES", "pipeline_dir", "restore_docstrings", "shipped_path", "specs_dir", "testing_dir"]


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


def testing_dir() -> Path:
    """The folder of :mod:`dyknow.testing`'s files: the paper's scenario specs (``scenario*.xml``)."""
    return Path(__file__).resolve().parent / "testing"


def pipeline_dir() -> Path:
    """The folder of :mod:`dyknow.demo.pipeline`'s files: the spec dyknow manages the pipeline
    robot with (``pipeline.xml``) and the robot's mode file (``modes.yaml``)."""
    return Path(__file__).resolve().parent / "demo" / "pipeline"


#: The names of the shipped folders on the command line, and what each holds.
SHIPPED_NAMES = {
    "@shipped": "dyknow's shipped specs and the example ontology (dyknow.ttl)",
    "@testing": "the scenario specs of dyknow.testing, whose stand-in units need no camera",
    "@pipeline": "the pipeline robot's managing spec and its system_modes mode file (dyknow.demo.pipeline)",
}
#: The kinds of file the shipped folders hold (what ``dyknow paths`` lists).
SHIPPED_FILES = (".xml", ".ttl", ".xsd", ".yaml")


def shipped_path(text: str) -> str:
    """``text`` with a leading shipped name replaced by its folder: ``@shipped`` (the shipped
    specs: :func:`specs_dir`), ``@shipped/dyknow.ttl`` (a file of it), ``@testing/scenario.xml``
    (:func:`testing_dir`); any other text unchanged.

    >>> shipped_path("specs/mine.xml")
    'specs/mine.xml'
    >>> shipped_path("@shipped/dyknow.ttl").endswith("dyknow.ttl")
    True

    Raises :class:`ValueError` naming the known names for an unknown one (``@shiped``), and
    :class:`FileNotFoundError` when the file named is not shipped.
    """
    if not text.startswith("@"):
        return text
    name, sep, rest = text.partition("/")
    if name not in SHIPPED_NAMES:
        from dyknow.errors import did_you_mean

        known = ", ".join(SHIPPED_NAMES)
        raise ValueError(f"{text}: no shipped folder {name!r}{did_you_mean(name, list(SHIPPED_NAMES))}; expected one of {known} (dyknow paths lists them)")
    folder = {"@shipped": specs_dir, "@testing": testing_dir, "@pipeline": pipeline_dir}[name]()
    path = folder / rest if rest else folder
    if not path.exists():
        there = ", ".join(sorted(p.name for p in folder.iterdir() if p.suffix in SHIPPED_FILES))
        raise FileNotFoundError(f"{text}: {path} is not shipped; {name} holds {there}")
    return str(path)


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
