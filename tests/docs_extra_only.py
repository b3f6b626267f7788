"""Run Sphinx as ``make docs`` runs it on a fresh clone, where only the ``docs`` extra is installed.

``python -m tests.docs_extra_only SPHINX-ARGS...`` builds the site with every module that only
another extra brings (Hypothesis of the ``test`` extra, rosbags of ``ros2``, pyzmq of ``bench``,
...) made unimportable, as it is in a virtual environment made by ``pip install -e '.[docs]'``.
Which distributions that environment has is computed from the installed metadata: dyknow's
requirements without an extra, those of the ``docs`` extra, and theirs, recursively, markers
evaluated; every other installed distribution's top-level modules raise ModuleNotFoundError.

A real fresh environment would cost a download and a mypyc build per run (minutes); this costs
one Sphinx build and fails the same way: ``make docs`` once failed on a fresh clone because the
reference imported ``dyknow.testing.fuzzing``, which needs Hypothesis.
"""

from __future__ import annotations

import importlib.abc
import importlib.metadata as metadata
import re
import sys
from collections.abc import Sequence
from types import ModuleType

from packaging.markers import default_environment
from packaging.requirements import Requirement


def _name(text: str) -> str:
    return re.sub(r"[-_.]+", "-", text).lower()


def allowed_distributions(project: str = "dyknow", extras: Sequence[str] = ("docs",)) -> set[str]:
    """The distributions ``pip install 'PROJECT[EXTRAS]'`` brings: their normalized names."""
    found: set[str] = set()
    todo: list[tuple[str, frozenset[str]]] = [(project, frozenset(extras))]
    while todo:
        name, wanted = todo.pop()
        key = _name(name)
        try:
            dist = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue  # a requirement not installed here (another platform's): nothing to allow
        if key in found and not wanted:
            continue
        found.add(key)
        for text in dist.requires or []:
            req = Requirement(text)
            if req.marker is not None:
                envs = [dict(default_environment(), extra=e) for e in (wanted or {""})]
                if not any(req.marker.evaluate(env) for env in envs):
                    continue
            if _name(req.name) not in found or req.extras:
                todo.append((req.name, frozenset(req.extras)))
    return found


def top_level_modules(dist: metadata.Distribution) -> set[str]:
    """The importable top-level names a distribution installs."""
    text = dist.read_text("top_level.txt")
    if text:
        return {line.strip() for line in text.splitlines() if line.strip()}
    names = set()
    for file in dist.files or []:
        first = file.parts[0]
        if first.endswith((".dist-info", ".egg-info", ".data")) or first in ("..", "__pycache__", "bin"):
            continue
        names.add(first.removesuffix(".py") if len(file.parts) == 1 else first)
    return {n for n in names if n.isidentifier()}


class Refuse(importlib.abc.MetaPathFinder):
    """Imports of the refused top-level modules fail as if they were not installed."""

    def __init__(self, refused: dict[str, str]) -> None:
        self.refused = refused

    def find_spec(self, fullname: str, path: object, target: ModuleType | None = None) -> None:
        top = fullname.partition(".")[0]
        if top in self.refused:
            raise ModuleNotFoundError(f"No module named {fullname!r} (of {self.refused[top]}, which the docs extra does not install)", name=fullname)
        return None


def refused_modules() -> dict[str, str]:
    """Top-level module -> distribution, for what an environment of the docs extra lacks."""
    allowed = allowed_distributions()
    keep: set[str] = set()
    for dist in metadata.distributions():
        if _name(dist.metadata["Name"]) in allowed:
            keep |= top_level_modules(dist)
    refused: dict[str, str] = {}
    for dist in metadata.distributions():
        name = _name(dist.metadata["Name"])
        if name in allowed or name in ("pip", "setuptools", "wheel"):
            continue
        for module in top_level_modules(dist) - keep - set(sys.stdlib_module_names):
            refused[module] = name
    return refused


def main(argv: Sequence[str]) -> int:
    """Build with Sphinx (``sphinx-build ARGV``) with only the docs extra importable."""
    # (a module a .pth file imported at start-up stays: nothing of dyknow's imports those)
    sys.meta_path.insert(0, Refuse(refused_modules()))
    from sphinx.cmd.build import main as sphinx_build

    return sphinx_build(list(argv))


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
