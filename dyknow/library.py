"""The library: the transformation specifications a manager knows, by label.

Adding a spec whose label is already known replaces it (the paper's AddTransformation allows
overriding). Every change bumps ``version`` so that readers (the planner) can tell a snapshot is
stale without comparing contents.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator

from dyknow.errors import LibraryError, did_you_mean
from dyknow.spec import TransformationSpec

__all__ = ["Library"]


class Library:
    """Transformation specifications by label. Thread-safe; iteration works on a snapshot."""

    def __init__(self, specs: Iterable[TransformationSpec] = ()) -> None:
        self._lock = threading.Lock()
        self._specs: dict[str, TransformationSpec] = {}
        self.version = 0
        self.add(specs)

    def add(self, specs: TransformationSpec | Iterable[TransformationSpec]) -> list[str]:
        """Store specs (replacing any with the same label); returns their labels."""
        batch = [specs] if isinstance(specs, TransformationSpec) else list(specs)
        for spec in batch:
            if not isinstance(spec, TransformationSpec):
                raise LibraryError(f"got {type(spec).__name__}", expected="a TransformationSpec")
        with self._lock:
            for spec in batch:
                self._specs[spec.label] = spec
            if batch:
                self.version += 1
        return [spec.label for spec in batch]

    def remove(self, label: str) -> bool:
        """Forget the spec with ``label``; returns whether there was one."""
        with self._lock:
            found = self._specs.pop(label, None) is not None
            if found:
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
