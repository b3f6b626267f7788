"""The manager's security policy: which code it loads, which files callers may name, what it bounds.

A manager's services are reachable by any Zenoh peer that reaches it, so what arrives through
them is hostile input. Three policies keep it harmless; the local Python API is trusted and
passes through unchecked (it runs as the operator):

- :class:`SourcePolicy`: the unit sources (``package.module:Class``) the manager may import. The
  packages ``dyknow`` and ``transformations``, the modules named by the specs the operator gave
  (at start, or through the Python API) and the operator's ``--allow-source`` patterns. A spec
  that names any other source is refused when it is added through the service; nothing is
  imported, and the module name is checked before every import anyway.
- :class:`DataRoots`: the folders that file params (``type="path"`` in a spec, or declared by the
  unit class in ``Unit.path_params``) may name when a unit is spawned for a remote caller or from
  a spec added remotely: writes under ``--data-root`` folders only, reads there and in the
  folders of the specs loaded at start. ``..``, ``~``, symlinks out of a root, absolute paths
  elsewhere, globs whose fixed part escapes and globs or folders a file of which resolves outside
  (a symbolic link inside a root) are refused, naming the param and nothing outside the roots.
- :class:`Limits`: the size of a request, the depth of its JSON, the length of names and keys
  (a key over Zenoh's batch size would make its transport panic), the expansions of a template,
  the entries and time a glob may take; the size and windows of a temporal formula and what a
  quantified one expands to, the memory and formula nodes the formula monitors share (and each
  caller's share of the nodes) and how far ahead a sample they take may be stamped
  (:mod:`dyknow.reasoning`); the size of the library, which the manager's summary carries to its
  peers; the signed calls remembered per caller against replays (:mod:`dyknow.identity`); the
  series a Prometheus scrape serves; and the references one caller may hold on a shared request.
"""

from __future__ import annotations

import fnmatch
import ipaddress
import os
import re
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from dyknow.errors import AccessError
from dyknow.keys import MAX_KEY_BYTES, MAX_NAME_BYTES

__all__ = ["DEFAULT_SOURCES", "PATH_MODES", "DataRoots", "Limits", "SourcePolicy", "bounded_glob", "is_loopback", "module_of"]

#: The packages whose units every manager may load.
DEFAULT_SOURCES: tuple[str, ...] = ("dyknow", "transformations")

#: What a file param is for: read an existing file, or write one.
PATH_MODES: tuple[str, ...] = ("read", "write")

_SOURCE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*")
_PATTERN = re.compile(r"[A-Za-z0-9_.*?\[\]!]+(?::[A-Za-z0-9_*?\[\]!]+)?")
_GLOB_MAGIC = re.compile(r"[*?\[]")


@dataclass(frozen=True, slots=True)
class Limits:
    """What one request, name, key, template or glob may cost; over it is refused, not attempted."""

    max_request_bytes: int = 1 << 20
    max_json_depth: int = 32
    max_name_bytes: int = MAX_NAME_BYTES
    max_key_bytes: int = MAX_KEY_BYTES
    max_expansions: int = 10_000
    max_glob_entries: int = 100_000
    max_glob_s: float = 2.0
    #: The most units a manager runs at once (spawned by anyone, requests included).
    max_units: int = 1000
    #: The largest message the manager's session takes in (data or call): Zenoh drops a larger
    #: one while reassembling it, so it never costs more memory than this.
    max_message_bytes: int = 64 << 20
    #: What a spec's expansions may cost, in bytes of their text (estimated before expanding).
    max_expansion_bytes: int = 16 << 20
    #: The most bytes one ``get_model`` reply holds; a larger model comes in pages.
    max_reply_bytes: int = 4 << 20
    #: The largest ROS 2 message a ``ros2:``/``ros2dds:`` input takes unless its binding says
    #: ``max_bytes=`` (an untyped input: at most 1 MiB); a larger one is dropped before it is
    #: copied or decoded (:data:`dyknow.ros2.node.DEFAULT_MAX_MESSAGE_BYTES`).
    max_ros2_message_bytes: int = 16 << 20
    #: The most nodes (atoms, constants, operators) a temporal formula may have: a monitor's cost
    #: per sample grows with them (``dyknow.reasoning.check_formula``).
    max_formula_nodes: int = 500
    #: The longest a formula's interval bound, and how far ahead it may look in all (its future
    #: horizon), in ns: one day. A verdict waits up to its horizon; a past operator that must look
    #: further back writes ``inf`` (which costs nothing per state over plain operands).
    max_window_ns: int = 86_400 * 1_000_000_000
    #: What a quantified formula (``forall c in Class: ...``) may expand to: individuals times
    #: the body's nodes, checked before anything is substituted.
    max_quantified_nodes: int = 20_000
    #: What the formula monitors of one manager keep together, in cells: a cell is one node's
    #: entry for one retained state (12-73 bytes measured, at most about 250 by construction), so
    #: 25-150 MB as measured, 0.5 GB at most. Each monitor's share is this over the monitors running; past it,
    #: the oldest states are given up, their pending verdicts unknown (``dyknow.reasoning.progression``).
    max_monitor_cells: int = 2_000_000
    #: The formula nodes the monitors of one manager have in all (requirements included): every
    #: sample costs each node of the formulas that read it a step.
    max_monitor_nodes: int = 20_000
    #: The share of ``max_monitor_nodes`` that one caller's monitors and requirements may hold in
    #: all (a caller: its certificate's name when its calls are signed, else its client), so that
    #: no caller takes what the others share: 5,000 nodes of 20,000.
    monitor_nodes_caller_share: float = 0.25
    #: The share of ``max_monitor_nodes`` that no caller may take: the manager's own watches (the
    #: requirements of its specs, the trials of its adaptations) and its Python API keep it
    #: (4,000 nodes of 20,000; the callers together hold at most the other 16,000).
    monitor_nodes_reserved_share: float = 0.2
    #: How far in the future (beyond its clock's uncertainty) a sample's time may lie for a monitor
    #: to take it, in ns: a later one would close every state before it and blind the monitor.
    max_future_ns: int = 100_000_000
    #: The most specs a manager's library holds, and their bytes as its summary carries them: a
    #: peer takes a summary of at most 16 MiB (``dyknow.federation.MAX_SUMMARY_BYTES``), which
    #: also carries the units and measurements.
    max_library_specs: int = 10_000
    max_library_bytes: int = 8 << 20
    #: The signed calls a manager remembers per caller (certificate common name) among those signed
    #: at or before its clock, within the 300 s a call's time may be off (``dyknow.identity``):
    #: past it the caller's oldest are forgotten and its floor rises to their time, never past the
    #: manager's clock (about 70 calls a second, sustained over the window).
    max_caller_calls: int = 20_000
    #: The signed calls a manager remembers per caller among those signed *ahead* of its clock (a
    #: clock ahead, or a forged time): each is kept until it leaves the window, so none raises
    #: the floor; past it a call signed ahead is refused, and calls signed on time are not.
    max_caller_calls_ahead: int = 20_000
    #: The most series one Prometheus scrape of the manager serves (``--metrics-port``; each
    #: histogram bucket is one, as Prometheus counts them; about 10 MB of text): a unit takes
    #: 2, 3 per output and 37 per input; past it the latest spawned units are left out whole,
    #: logged and counted (``dyknow.metrics``). A unit's series go with the unit.
    max_metric_series: int = 100_000
    #: The most references one caller may hold on one request, kept and held alike: a caller is
    #: a certificate's common name on a manager with roles (all its clients together), a client
    #: id without (``dyknow.model.Owner.same_caller``). Past it that caller's next request of the
    #: tag is refused, and everyone else's still goes through (``dyknow.holders`` counts the
    #: callers of a request, not their clients). The manager's own Python API is not bounded.
    max_references_per_caller: int = 256


_DEFAULT = Limits()


def module_of(source: str) -> str:
    """The module part of a source ``package.module:Class``."""
    return source.partition(":")[0]


class SourcePolicy:
    """The unit sources a manager may import: module prefixes, globs, or exact sources.

    A pattern ``pkg`` allows ``pkg`` and its submodules; ``pkg.units*`` is a glob on the module
    name; ``pkg.units:Camera`` allows that one class.
    """

    def __init__(self, patterns: Iterable[str] = DEFAULT_SOURCES) -> None:
        self._patterns: list[str] = []
        self.allow(*patterns)

    @property
    def patterns(self) -> tuple[str, ...]:
        """The patterns allowed, in the order they were added."""
        return tuple(self._patterns)

    def allow(self, *patterns: str) -> None:
        """Allow more sources (an operator's choice: ``--allow-source``, or a spec loaded locally)."""
        for pattern in patterns:
            if not isinstance(pattern, str) or not _PATTERN.fullmatch(pattern):
                raise AccessError(
                    f"{pattern!r} is not a source pattern",
                    where="allow_sources",
                    expected="a module such as mypkg or mypkg.units, a glob such as mypkg.*, or mypkg.units:Class",
                )
            if pattern not in self._patterns:
                self._patterns.append(pattern)

    def allows(self, source: str) -> bool:
        """Whether ``source`` (``package.module:Class``) may be imported."""
        if not _SOURCE.fullmatch(source):
            return False
        module = module_of(source)
        for pattern in self._patterns:
            if ":" in pattern:
                if fnmatch.fnmatchcase(source, pattern):
                    return True
            elif module == pattern or module.startswith(pattern + ".") or fnmatch.fnmatchcase(module, pattern):
                return True
        return False

    def check(self, source: str, where: str) -> None:
        """Raise :class:`AccessError` unless ``source`` may be imported; nothing is imported."""
        if not _SOURCE.fullmatch(source):
            raise AccessError(f"source {source!r} is not importable", where=where, expected="'package.module:Class'")
        if not self.allows(source):
            raise AccessError(
                f"source {source!r} is not allowed on this manager",
                where=where,
                expected="a unit of " + ", ".join(self._patterns) + " (the operator allows more with --allow-source PATTERN)",
            )


class DataRoots:
    """The folders file params may name for remote callers: ``read`` and ``write`` roots.

    A ``write`` root (``--data-root``) must be an existing folder: :class:`AccessError` naming it."""

    def __init__(self, write: Iterable[str | os.PathLike[str]] = (), read: Iterable[str | os.PathLike[str]] = ()) -> None:
        write = list(write)
        for folder in write:  # (a root that is not there would refuse every file named under it, silently until then)
            if not Path(folder).is_dir():
                why = "is not a folder" if Path(folder).exists() else "does not exist"
                raise AccessError(
                    f"{os.fspath(folder)} {why}",
                    where=f"--data-root {os.fspath(folder)}",
                    expected=f"an existing folder for the files remote callers may name (mkdir -p {os.fspath(folder)})",
                )
        self.write: tuple[Path, ...] = tuple(dict.fromkeys(Path(os.path.realpath(p)) for p in write))
        # whatever may be written may be read too
        self.read: tuple[Path, ...] = tuple(dict.fromkeys([*self.write, *(Path(os.path.realpath(p)) for p in read)]))

    def roots(self, mode: str) -> tuple[Path, ...]:
        """The roots of ``mode`` ("read" or "write")."""
        return self.write if mode == "write" else self.read

    def resolve(self, value: object, mode: str, where: str) -> str:
        """The absolute, symlink-free path ``value`` names, once it is known to lie under a root.

        A relative path is taken relative to the first root of ``mode``. A glob (reads only) is
        checked through its fixed leading folders. Raises :class:`AccessError` naming ``where``.
        """
        roots = self.roots(mode)
        listing = ", ".join(str(r) for r in roots)
        if not roots:
            raise AccessError(
                f"a remote caller may not name files to {mode}",
                where=where,
                expected="a manager started with --data-root DIR" + (" (or a spec folder, for reads)" if mode == "read" else ""),
            )
        if not isinstance(value, str) or not value.strip() or "\x00" in value or len(value) > 4096:
            raise AccessError(f"got {value!r}", where=where, expected=f"a path under {listing}")
        text = value.strip()
        parts = Path(text).parts
        if ".." in parts or text.startswith("~"):
            raise AccessError(f"{text!r} leaves its folder ('..' or '~')", where=where, expected=f"a path under {listing}")
        candidate = Path(text) if os.path.isabs(text) else roots[0] / text
        if _GLOB_MAGIC.search(text):
            if mode == "write":
                raise AccessError(f"{text!r} is a glob", where=where, expected="one file to write")
            fixed = []
            for part in candidate.parts:
                if _GLOB_MAGIC.search(part):
                    break
                fixed.append(part)
            self._inside(Path(*fixed), roots, text, where, listing)
            pattern = str(Path(os.path.realpath(Path(*fixed))).joinpath(*candidate.parts[len(fixed) :]))
            self._matches_inside(bounded_glob(pattern), roots, text, where, listing)
            return pattern
        resolved = Path(os.path.realpath(candidate))
        self._inside(resolved, roots, text, where, listing)
        if mode == "read" and resolved.is_dir():  # a folder's files are read too (a folder of images, say)
            self._matches_inside(_entries(resolved), roots, text, where, listing)
        return str(resolved)

    @staticmethod
    def _matches_inside(matches: Iterable[str], roots: Sequence[Path], text: str, where: str, listing: str) -> None:
        """Refuse ``text`` when a file it names resolves outside the roots (through a symbolic
        link inside them), saying nothing of what lies outside."""
        for match in matches:
            real = Path(os.path.realpath(match))
            if not any(real == root or root in real.parents for root in roots):
                raise AccessError(
                    f"{text!r} reaches outside the data roots through a symbolic link",
                    where=where,
                    expected=f"files that lie under {listing}",
                )

    @staticmethod
    def _inside(path: Path, roots: Sequence[Path], text: str, where: str, listing: str) -> None:
        real = Path(os.path.realpath(path))
        if not any(real == root or root in real.parents for root in roots):
            raise AccessError(f"{text!r} is outside the data roots", where=where, expected=f"a path under {listing}")


def bounded_glob(pattern: str, *, max_entries: int = _DEFAULT.max_glob_entries, max_s: float = _DEFAULT.max_glob_s) -> list[str]:
    """The files a glob pattern matches, visiting at most ``max_entries`` entries within ``max_s``.

    Unlike :func:`glob.glob`, a pattern such as ``/*/*/*/*/*.x`` cannot walk the whole file
    system: past either bound it raises :class:`AccessError` naming the pattern.
    """
    deadline = time.monotonic() + max_s
    path = Path(pattern)
    anchor = Path(path.anchor) if path.is_absolute() else Path(".")
    current = [anchor]
    visited = 0
    parts = path.parts[1:] if path.is_absolute() else path.parts
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        found: list[Path] = []
        for folder in current:
            if not _GLOB_MAGIC.search(part):
                candidate = folder / part
                if candidate.exists():
                    found.append(candidate)
                continue
            try:
                with os.scandir(folder) as entries:
                    for entry in entries:
                        visited += 1
                        if visited > max_entries or time.monotonic() > deadline:
                            raise AccessError(
                                f"the glob {pattern!r} is too costly (over {max_entries} entries or {max_s:g} s)",
                                expected="a pattern whose folders are named, such as frames/*.png",
                            )
                        if entry.name.startswith(".") and not part.startswith("."):
                            continue
                        if fnmatch.fnmatchcase(entry.name, part) and (last or _is_dir(entry)):
                            found.append(Path(entry.path))
            except OSError:  # an unreadable folder matches nothing
                continue
        current = found
    return sorted(str(p) for p in current)


def _entries(folder: Path, max_entries: int = _DEFAULT.max_glob_entries) -> list[str]:
    """The entries of ``folder``; :class:`AccessError` when it has more than ``max_entries``."""
    found: list[str] = []
    try:
        with os.scandir(folder) as entries:
            for entry in entries:
                found.append(entry.path)
                if len(found) > max_entries:
                    raise AccessError(f"the folder {folder} has over {max_entries} entries", expected="a smaller folder")
    except OSError:  # unreadable: the unit will say so
        return []
    return found


def _is_dir(entry: os.DirEntry[str]) -> bool:
    try:
        return entry.is_dir()
    except OSError:  # unreadable (another user's /proc entry, say): not ours to walk
        return False


def is_loopback(host: str) -> bool:
    """Whether ``host`` is ``localhost`` or a loopback address (only this machine can connect)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.split("%")[0]).is_loopback
    except ValueError:
        return False
