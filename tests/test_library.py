"""The library of transformation specs."""

from __future__ import annotations

import pytest

from dyknow import Library, LibraryError, TransformationSpec
from dyknow.spec import Port


def spec(label: str, source: str = "m:C") -> TransformationSpec:
    return TransformationSpec(label=label, source=source, ports=(Port("o", "out"),))


def test_add_override_remove_and_versions() -> None:
    library = Library([spec("a")])
    v0 = library.version
    assert library.add([spec("b"), spec("a", "m:D")]) == ["b", "a"]
    assert library.get("a").source == "m:D" and len(library) == 2
    assert library.version > v0
    assert library.remove("a") and not library.remove("a")
    assert library.labels() == ["b"] and "b" in library and "a" not in library


def test_unknown_label_lists_known_ones_and_suggests() -> None:
    library = Library([spec("relay"), spec("periodic-source")])
    with pytest.raises(LibraryError, match=r"no transformation labelled 'rely'; expected one of the known labels: 'periodic-source', 'relay' \(did you mean 'relay'\?\)") as error:
        library.get("rely")
    assert error.value.what == "no transformation labelled 'rely'"
    assert error.value.expected == "one of the known labels: 'periodic-source', 'relay' (did you mean 'relay'?)"
    with pytest.raises(LibraryError, match="expected a TransformationSpec"):
        library.add(["not a spec"])  # type: ignore[list-item]
