"""The library: the transformation specifications a manager knows, by label.

Adding a spec whose label is already known replaces it (the paper's AddTransformation allows
overriding). Every change bumps ``version`` so that readers (the planner) can tell a snapshot is
stale without comparing contents.

A library may be bounded (``max_specs``, ``max_bytes``): a manager's summary carries every spec
of its library to the other managers, and a peer takes a summary of at most 16 MiB
(:data:`dyknow.federation.MAX_SUMMARY_BYTES`), so the manager bounds the library as a whole, not
only each call that adds to it (``Limits.max_library_specs``, ``Limits.max_library_bytes``). A
spec's size is that of its XML as a summary carries it, a JSON string. An add that would pass a
bound is refused whole, naming the bound; nothing of it is stored.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable, Iterator

from dyknow.errors import LibraryError, did_you_mean
from dyknow.spec import TransformationSpec

__all__ = ["Library", "spec_bytes"]


def spec_bytes(spec: TransformationSpec) -> int:
    """The bytes ``spec`` takes in a manager's summary: its XML as a JSON string."""
    return len(json.dumps(spec.to_xml()))


def _count(bound: int | None) -> str:
    return "any number of" if bound is None else f"{bound:,}"


class Library:
    """Transformation specifications by label, at most ``max_specs`` of them and ``max_bytes`` in
    all (None: no bound). Thread-safe; iteration works on a snapshot."""

    def __init__(self, specs: Iterable[TransformationSpec] = (), *, max_specs: int | None = None, max_bytes: int | None = None) -> None:
        self._lock = threading.Lock()
        self._specs: dict[str, TransformationSpec] = {}
        self._sizes: dict[str, int] = {}
        self.max_specs = max_specs
        self.max_bytes = max_bytes
        #: the bytes of every spec held, as a summary carries them (see the module documentation)
        self.bytes = 0
        self.version = 0
        self.add(specs)

    def add(self, specs: TransformationSpec | Iterable[TransformationSpec]) -> list[str]:
        """Store specs (replacing any with the same label); returns their labels.

        :class:`LibraryError` naming the bound, with nothing stored, when the library would hold
        more than ``max_specs`` specs or ``max_bytes`` bytes after it.
        """
        batch = [specs] if isinstance(specs, TransformationSpec) else list(specs)
        for spec in batch:
            if not isinstance(spec, TransformationSpec):
                raise LibraryError(f"got {type(spec).__name__}", expected="a TransformationSpec")
        sizes = {spec.label: spec_bytes(spec) for spec in batch} if self.max_bytes is not None else dict.fromkeys((s.label for s in batch), 0)
        with self._lock:
            count = len(self._specs) + sum(1 for label in sizes if label not in self._specs)
            total = self.bytes + sum(size - self._sizes.get(label, 0) for label, size in sizes.items())
            over = []
            if self.max_specs is not None and count > self.max_specs:
                over.append(f"{count:,} specs")
            if self.max_bytes is not None and total > self.max_bytes:
                over.append(f"{total:,} bytes")
            if over:
                raise LibraryError(
                    f"adding {len(sizes):,} specs would make the library {' and '.join(over)}",
                    where="library",
                    expected=f"at most {_count(self.max_specs)} specs and {_count(self.max_bytes)} bytes of them "
                    "(Limits.max_library_specs, max_library_bytes: a peer takes a summary of at most 16 MiB); "
                    "remove some first (remove_transformation)",
                )
            for spec in batch:
                self._specs[spec.label] = spec
            self._sizes.update(sizes)
            self.bytes = total
            if batch:
                self.version += 1
        return [spec.label for spec in batch]

    def remove(self, label: str) -> bool:
        """Forget the spec with ``label``; returns whether there was one."""
        with self._lock:
            found = self._specs.pop(label, None) is not None
            if found:
                self.bytes -= self._sizes.pop(label, 0)
                self.version += 1
            return found

    def get(self, label: str) -> TransformationSpec:
        """The spec with ``label``; :class:`LibraryError` with close matches when unknown."""
        spec = self._specs.get(label)
        if spec is None:
            known = list(self._specs)
            listing = ", ".join(repr(k) for k in sorted(known)[:12]) or "none (add specs with --specs or add_transformation)"
            raise LibraryError(
                f"no transformation labelled {label!r}", expected=f"one of the known labels: {listing}{did_you_mean(label, known)}"
            )
        return spec

    def specs(self) -> tuple[TransformationSpec, ...]:
        """A snapshot of every spec, in the order they were added."""
        with self._lock:
            return tuple(self._specs.values())

    def labels(self) -> list[str]:
        """The labels, in the order the specs were added."""
        with self._lock:
            return list(self._specs)

    def __contains__(self, label: object) -> bool:
        return label in self._specs

    def __len__(self) -> int:
        return len(self._specs)

    def __iter__(self) -> Iterator[TransformationSpec]:
        return iter(self.specs())
