"""Build hook: compile dyknow's hot-path modules with mypyc (see docs/performance.md).

The modules listed in ``COMPILED`` run once per message and per hop: compiled to C by mypyc they
take about half the time they take interpreted (``python benchmarks/chain.py``). The temporal
monitor (``dyknow/reasoning/progression.py`` and its nodes: ``nodes``, ``aggregates``, ``past``,
``future``, ``windows``, ``pending``, ``timeline``; with the values and atoms of ``values.py``) runs once per
state: compiled it costs a quarter to a third of its interpreted time (0.21 against 0.71 us per
state for ``once[0, 100ms] x > 0.9``, 3.9 against 8.5 us for a future formula of 5 operators).
``objects.py`` runs a ``foreach`` formula's samples to their objects' monitors, and makes and
ends a monitor per object (``python benchmarks/reasoning.py --churn 20000``); ``served.py`` hands
each sample to the formulas a monitor unit serves. They stay plain,
type-checked Python: the same source runs interpreted when

- ``DYKNOW_PURE_PYTHON=1`` is set at install time (to debug or profile them as Python), or
- no C compiler is found (a warning says so; everything works, only slower).

An editable install compiles them in place: after changing one of them, install again
(``make test`` and ``make demo`` do it), or the compiled copy keeps shadowing the source.

Compiling is most of a first install's time: about 2 minutes on a quiet 2-core machine, up to 6
on a loaded one. Each step prints a line starting with ``dyknow:`` (``pip install -v`` shows
them; the Makefile's ``tools/install.py`` shows them with pip quiet). mypyc runs only for the
commands that build the extensions, not for pip's metadata steps, which run this file too.
"""

from __future__ import annotations

import os
import shutil
import sys
import sysconfig
import time

from setuptools import setup
from setuptools.command.build_ext import build_ext

COMPILED = [
    "dyknow/bus.py",
    "dyknow/executor.py",
    "dyknow/message.py",
    "dyknow/proxy/job.py",
    "dyknow/proxy/ports.py",
    "dyknow/proxy/proxy.py",
    "dyknow/reasoning/aggregates.py",
    "dyknow/reasoning/evaluator.py",
    "dyknow/reasoning/future.py",
    "dyknow/reasoning/nodes.py",
    "dyknow/reasoning/objects.py",
    "dyknow/reasoning/past.py",
    "dyknow/reasoning/pending.py",
    "dyknow/reasoning/progression.py",
    "dyknow/reasoning/semantics.py",
    "dyknow/reasoning/served.py",
    "dyknow/reasoning/timeline.py",
    "dyknow/reasoning/values.py",
    "dyknow/reasoning/windows.py",
    "dyknow/receiver.py",
    "dyknow/stats.py",
    "dyknow/transport/entities.py",
    "dyknow/transport/runtime.py",
    "dyknow/transport/session.py",
    "dyknow/transport/shared_memory.py",
]


def _compiler() -> str | None:
    cc = (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()[0]
    return shutil.which(cc)


#: The setup.py commands that build extensions; the others (egg_info, dist_info: pip's metadata
#: steps) need no mypyc run.
BUILDS = {"build", "build_ext", "bdist_wheel", "editable_wheel", "develop", "install"}

#: The commands that install in place (the source tree is what Python imports): only these leave
#: compiled modules beside the sources, and only these remove them for a pure install. A wheel
#: built from a checkout (``pip wheel .``) takes the sources alone and leaves the checkout as it was.
IN_PLACE = {"editable_wheel", "develop"}


def say(text: str) -> None:
    """A progress line (``tools/install.py`` shows the lines that start with ``dyknow:``)."""
    print(f"dyknow: {text}", file=sys.stderr, flush=True)


def ext_modules() -> list:
    """The mypyc extensions, or none when pure Python is asked for or cannot be avoided."""
    if not BUILDS & set(sys.argv[1:]):
        return []
    if os.environ.get("DYKNOW_PURE_PYTHON"):
        if IN_PLACE & set(sys.argv[1:]) or {"build_ext", "--inplace"} <= set(sys.argv[1:]):
            _remove_compiled()
        return []
    if _compiler() is None:
        say("no C compiler found: installing the hot-path modules as pure Python (slower)")
        return []
    from mypyc.build import mypycify

    started = time.monotonic()
    say(f"compiling {len(COMPILED)} hot-path modules with mypyc (about 2 minutes, up to 6 on a loaded machine; "
        "DYKNOW_PURE_PYTHON=1 skips it, and they run about half as fast): type-checking and writing C")  # fmt: skip
    # mypy takes the types of dyknow's dependencies as Any, installed or not, so every build
    # compiles the same checks (the build environment of a plain install has none of them)
    found = mypycify(["--no-site-packages", "--ignore-missing-imports", *COMPILED], opt_level="3")
    say(f"wrote C in {time.monotonic() - started:.0f} s; compiling it ({len(found)} extensions)")
    return found


def _remove_compiled() -> None:
    """Remove what an earlier compiled install left in place (an editable install compiles in the
    source tree): those copies would shadow the sources, and their shared helper module is no longer
    importable once the install is pure Python."""
    here = os.path.dirname(os.path.abspath(__file__))
    stale = [os.path.join(here, name) for name in os.listdir(here) if "__mypyc." in name and name.endswith((".so", ".pyd"))]
    for module in COMPILED:
        folder, base = os.path.split(os.path.join(here, module[:-3]))
        if os.path.isdir(folder):
            stale += [os.path.join(folder, n) for n in os.listdir(folder) if n.startswith(base + ".") and n.endswith((".so", ".pyd"))]
    for path in stale:
        os.remove(path)
    if stale:
        say(f"DYKNOW_PURE_PYTHON: removed {len(stale)} compiled modules an earlier install left beside the sources")


class ProgressBuildExt(build_ext):
    """build_ext that says which extension it compiles, and how long each took."""

    def build_extensions(self) -> None:
        self._done = 0
        super().build_extensions()

    def build_extension(self, ext) -> None:  # type: ignore[no-untyped-def]
        started = time.monotonic()
        super().build_extension(ext)
        self._done += 1
        say(f"compiled {ext.name} ({self._done}/{len(self.extensions)}) in {time.monotonic() - started:.0f} s")


setup(ext_modules=ext_modules(), cmdclass={"build_ext": ProgressBuildExt})
