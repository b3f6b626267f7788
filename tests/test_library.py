"""The library of transformation specs."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import pytest

from dyknow import Client, Library, LibraryError, Manager, SpecError, TransformationSpec
from dyknow.federation import MAX_SUMMARY_BYTES, Summary
from dyknow.library import spec_bytes
from dyknow.security import Limits
from dyknow.spec import Port, Tag
from tests.conftest import GENERIC_SPECS, free_port


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
    with Client(manager.name, connect=manager.endpoints, timeout_s=60) as client:  # (an add of 1,000 specs of 3.4 MB takes seconds on a loaded machine)
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


WATCHED = """<transformations>
<transformation><label>watched-{name}</label><source>transformations.generic:Relay</source>
  <ports><port type="in">in</port><port type="out">out</port></ports>
  <tags><tag port="out">Track(x)</tag></tags>
  <requirements><requirement>{requirement}</requirement></requirements>
</transformation></transformations>"""
TOO_LONG = "always[0, 172800s] Track(x).ok"  # a window of two days: a manager's longest is one (Limits.max_window_ns)
TOO_BIG = " or ".join(f"Track(x).n > {k}" for k in range(300))  # 599 nodes: at most 500 (Limits.max_formula_nodes)


def test_a_spec_requirement_over_the_formula_bounds_is_refused_when_added(make_manager: Callable[..., Manager], tmp_path: Path) -> None:
    """Issue 51, item 10: a spec whose requirement is over the formula bounds was added, then its
    requirement could not be watched, so a request it served ran unwatched, with one log line.
    It is refused when added now, through the service, the Python API and at start, naming the
    file and line, the requirement and the bound; nothing of it is stored and what runs, runs on."""
    manager = make_manager(listen=[f"tcp/127.0.0.1:{free_port()}"])
    manager.spawn("periodic-source", "ticks", params={"rate_hz": 10})
    labels, version = manager.library.labels(), manager.library.version
    window = tmp_path / "window.xml"
    window.write_text(WATCHED.format(name="window", requirement=TOO_LONG))
    nodes = tmp_path / "nodes.xml"
    nodes.write_text(WATCHED.format(name="nodes", requirement=TOO_BIG))
    with Client(manager.name, connect=manager.endpoints) as client:
        with pytest.raises(SpecError) as caught:
            client.add_transformation(window)
        assert str(caught.value) == (
            f"{window}:5: <requirement>: formula column 7: 'always[0, 172800s]' has the bound 172800s, beyond the longest window "
            f"in '{TOO_LONG}'; expected bounds of at most 86400s (Limits.max_window_ns)"
        )
        with pytest.raises(SpecError, match=rf"^{re.escape(str(nodes))}:5: <requirement>: formula column \d+: the formula has more than 500 nodes"):
            client.add_transformation(nodes)
    with pytest.raises(SpecError, match=r"^<add_transformation>:5: <requirement>: .*has the bound 172800s.*Limits\.max_window_ns"):
        manager.add_transformation(WATCHED.format(name="window", requirement=TOO_LONG))
    built = TransformationSpec(
        label="watched-python",
        source="transformations.generic:Relay",
        ports=(Port("in", "in"), Port("out", "out")),
        tags=(Tag("out", "Track(x)"),),
        requirements=(TOO_LONG,),
    )
    with pytest.raises(SpecError, match=r"^<memory>: <requirement> 'always\[0, 172800s\] Track\(x\)\.ok': formula column 7: .*172800s"):
        manager.add_transformation(built)
    assert manager.library.labels() == labels and manager.library.version == version
    assert manager.has_unit("ticks")
    with pytest.raises(SpecError, match=r"window\.xml:5: <requirement>: .*Limits\.max_window_ns"):
        make_manager(specs=[GENERIC_SPECS, window])  # at start: the manager does not start
    # the bound is the manager's own: one whose windows may span three days takes the spec
    roomy = make_manager(limits=Limits(max_window_ns=3 * 86_400 * 1_000_000_000))
    assert roomy.add_transformation(window) == ["watched-window"]
