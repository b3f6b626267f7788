"""Build hook: compile dyknow's hot-path modules with mypyc (see docs/performance.md).

The modules listed in ``COMPILED`` run once per message and per hop: compiled to C by mypyc they
take about half the time they take interpreted (``python benchmarks/chain.py``). The temporal
monitor (``dyknow/reasoning/progression.py``, with the atoms of ``semantics.py``) runs once per
state: compiled it costs a quarter to a third of its interpreted time (0.21 against 0.71 us per
state for ``once[0, 100ms] x > 0.9``, 3.9 against 8.5 us for a future formula of 5 operators). They stay plain,
type-checked Python: the same source runs interpreted when

- ``DYKNOW_PURE_PYTHON=1`` is set at install time (to debug or profile them as Python), or
- no C compiler is found (a warning says so; everything works, only slower).

An editable install compiles them in place: after changing one of them, install again
(``make test`` and ``make demo`` do it), or the compiled copy keeps shadowing the source.
"""

from __future__ import annotations

import os
import shutil
import sys
import sysconfig

from setuptools import setup

COMPILED = [
    "dyknow/bus.py",
    "dyknow/executor.py",
    "dyknow/message.py",
    "dyknow/proxy.py",
    "dyknow/reasoning/progression.py",
    "dyknow/reasoning/semantics.py",
    "dyknow/receiver.py",
    "dyknow/stats.py",
    "dyknow/transport.py",
]


def _compiler() -> str | None:
    cc = (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()[0]
    return shutil.which(cc)


def ext_modules() -> list:
    """The mypyc extensions, or none when pure Python is asked for or cannot be avoided."""
    if os.environ.get("DYKNOW_PURE_PYTHON"):
        return []
    if _compiler() is None:
        print("dyknow: no C compiler found: installing the hot-path modules as pure Python (slower)", file=sys.stderr)
        return []
    from mypyc.build import mypycify

    # mypy takes the types of dyknow's dependencies as Any, installed or not, so every build
    # compiles the same checks (the build environment of a plain install has none of them)
    return mypycify(["--no-site-packages", "--ignore-missing-imports", *COMPILED], opt_level="3")


setup(ext_modules=ext_modules())
