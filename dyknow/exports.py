"""The public names of a package, imported when first used (PEP 562).

``import dyknow`` and the ``dyknow`` command must start fast: a command that only parses its
options, or reports that no manager is there, should not import the planner, the ontology's
rdflib, numpy and the rest of the middleware first (``dyknow --help`` took 0.55 s, 0.44 s of it
importing ``dyknow``). A package lists where each public name lives; :func:`lazy_exports` gives it
the module ``__getattr__`` and ``__dir__`` that import the defining module on first access.
``from dyknow import Manager`` and ``dyknow.Manager`` work as before; type checkers read the
package's ``if TYPE_CHECKING:`` imports of the same names.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, namespace: dict[str, Any], where: Mapping[str, str], after: Callable[[str, Any], None] | None = None
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """A package's ``__getattr__`` and ``__dir__``: ``where`` maps each public name to the module
    that defines it; ``after(name, value)`` runs once on each value imported (to restore a
    docstring, say). A name not in ``where`` that is a submodule of ``package`` is imported as
    one (``dyknow.spec`` after a bare ``import dyknow``). The value is stored in ``namespace`` (the
    package's ``globals()``), so each name is looked up once.
    """

    def __getattr__(name: str) -> Any:
        module = where.get(name)
        if module is None:
            if name.startswith("__"):
                raise AttributeError(f"module {package!r} has no attribute {name!r}")
            try:
                value: Any = importlib.import_module(f"{package}.{name}")
            except ModuleNotFoundError as exc:
                if exc.name != f"{package}.{name}":
                    raise
                raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        else:
            value = getattr(importlib.import_module(module), name)
            if after is not None:
                after(name, value)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(where))

    return __getattr__, __dir__
