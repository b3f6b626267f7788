"""The library of transformation specs."""

from __future__ import annotations

import json
from collections.abc import Callable

import pytest

from dyknow import Client, Library, LibraryError, Manager, TransformationSpec
from dyknow.federation import MAX_SUMMARY_BYTES, Summary
from dyknow.library import spec_bytes
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


def test_a_bounded_library_refuses_what_would_pass_its_bounds_whole() -> None:
    library = Library([spec("a"), spec("b")], max_specs=3, max_bytes=3 * spec_bytes(spec("a")) + 10)
    assert library.bytes == 2 * spec_bytes(spec("a"))
    with pytest.raises(LibraryError) as many:
        library.add([spec("c"), spec("d")])
    assert many.value.what.startswith("adding 2 specs would make the library 4 specs")
    assert "at most 3 specs" in (many.value.expected or "") and "16 MiB" in (many.value.expected or "")
    assert library.labels() == ["a", "b"]  # nothing of it stored
    assert library.add([spec("a", "m:D"), spec("c")]) == ["a", "c"]  # a replacement takes no more room
    large = TransformationSpec(label="e", source="m:C", description="x" * 200, ports=(Port("o", "out"),))
    assert library.remove("c")
    with pytest.raises(LibraryError, match=r"would make the library [0-9,]+ bytes"):
        library.add(large)
    assert library.bytes == sum(spec_bytes(s) for s in library.specs())


LARGE = """<transformation><label>big-${{X}}-{round}</label><source>dyknow.testing:Source</source>
  <description>{text} ${{X}}</description>
  <args><arg label="X">{{{values}}}</arg></args>
  <ports><port type="out">out</port></ports></transformation>"""


def test_repeated_adds_cannot_grow_the_summary_beyond_what_peers_take(make_manager: Callable[..., Manager]) -> None:
    """Issue 38: each add was bounded (16 MiB of expansions) but the library was not: four adds
    gave a 56 MiB summary, which every peer refuses (16 MiB at most). The library as a whole is
    bounded now: the add that would pass it is refused, naming the bound, and the summary stays
    within what peers take."""
    manager = make_manager(listen=["tcp/127.0.0.1:0"])
    xml = LARGE.format(text="y" * 3000, values="; ".join(f"v{k}" for k in range(1000)), round="{round}")
    refused = None
    with Client(manager.name, connect=manager.endpoints) as client:
        for n in range(6):  # about 3.4 MB of XML each
            try:
                client.add_transformation(xml.replace("{round}", str(n)))
            except LibraryError as exc:
                refused = (n, exc)
                break
    assert refused is not None, "every add was taken"
    n, error = refused
    assert n >= 2 and error.what.startswith("adding 1,000 specs would make the library") and "8,388,608 bytes" in (error.expected or "")
    assert not any(label.startswith(f"big-v0-{n}") for label in manager.library.labels())
    summary = json.dumps(manager.summary().to_dict()).encode()
    assert len(summary) <= MAX_SUMMARY_BYTES
    Summary.from_json(summary, manager.name)  # what a peer does with it: taken
