"""A harness that runs one unit for a test: feed its input ports, read what its output ports send.

The unit runs as it would in production, in a manager of its own (in-process, serving nothing and
listening nowhere), wired to a :class:`~dyknow.testing.Source` per input port and a
:class:`~dyknow.testing.Sink` per output port::

    from dyknow.testing import UnitHarness

    def test_doubler():
        with UnitHarness("specs/doubler.xml", "doubler", params={"factor": 3}) as harness:
            harness.send("in", 2)
            assert harness.wait_for("out", 1)[0].payload == 6
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from dyknow.errors import LibraryError
from dyknow.manager import Manager
from dyknow.message import Message
from dyknow.model import UnitInfo
from dyknow.ontology import Ontology
from dyknow.proxy import UnitStatistics
from dyknow.spec import Port, TransformationSpec, load_specs, parse_specs
from dyknow.testing.units import Sink, Source
from dyknow.unit import Unit

__all__ = ["UnitHarness"]

_SOURCE = TransformationSpec(
    label="dyknow-testing-source", source="dyknow.testing:Source", ports=(Port("out", "out"),), description="feeds a unit under test"
)
_SINK_QUEUE = 1 << 16
_SINK = TransformationSpec(
    label="dyknow-testing-sink",
    source="dyknow.testing:Sink",
    ports=(Port("in", "in", queue=_SINK_QUEUE),),  # a burst (a monitor's flush) is recorded whole, not dropped
    description="records a unit's output",
)


class UnitHarness:
    """Runs one unit in a private manager; a context manager (``close()`` is safe twice).

    ``spec`` is a :class:`TransformationSpec`, a spec file (or directory), or XML text; ``label``
    picks the transformation when it holds several. ``params`` override the spec's params as at
    spawn time; ``ontology`` resolves template args over ontology classes. The unit is named
    ``name``; it is spawned at once, so a failing ``setup()`` shows in :attr:`info` (``state``
    ``"failed"`` and the error) rather than as an exception.
    """

    def __init__(
        self,
        spec: TransformationSpec | str | os.PathLike[str],
        label: str | None = None,
        *,
        params: Mapping[str, Any] | None = None,
        ontology: Ontology | None = None,
        name: str = "unit",
    ) -> None:
        chosen = _choose(spec, label, ontology)
        self.name = name
        self.spec = chosen
        self.manager = Manager("testing", specs=[chosen, _SOURCE, _SINK], listen=[], serve=False, ontology=ontology)
        try:
            self._sinks: dict[str, Sink] = {}
            self._sources: dict[str, Source] = {}
            for port in chosen.outputs:  # consumers first: nothing the unit sends is lost
                sink_name = f"recv-{port.name}"
                self.manager.spawn(_SINK.label, sink_name, bindings={"in": f"testing/{name}/out/{port.name}"})
                self._sinks[port.name] = _unit_as(self.manager.unit(sink_name), Sink)
            inputs = {p.name: f"testing/{name}/in/{p.name}" for p in chosen.inputs}
            outputs = {p.name: f"testing/{name}/out/{p.name}" for p in chosen.outputs}
            self.manager.spawn(chosen.label, name, params=params, bindings={**inputs, **outputs})
            for input_port, key in inputs.items():
                source_name = f"send-{input_port}"
                self.manager.spawn(_SOURCE.label, source_name, bindings={"out": key})
                self._sources[input_port] = _unit_as(self.manager.unit(source_name), Source)
        except BaseException:
            self.manager.close()
            raise

    def __enter__(self) -> UnitHarness:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the unit (its ``teardown()`` runs) and the manager; safe twice."""
        self.manager.close()

    @property
    def unit(self) -> Unit:
        """The unit under test (its Python object)."""
        return self.manager.unit(self.name)

    @property
    def info(self) -> UnitInfo:
        """The unit as the model shows it: state, bindings, error and traceback."""
        return self.manager.get_model().unit(self.name)

    def statistics(self) -> UnitStatistics:
        """The unit's statistics: per-port messages, drops, rejections and latency."""
        return self.manager.get_statistics(self.name)

    def send(self, port: str, payload: Any, *, origin_ns: int | None = None) -> None:
        """Deliver ``payload`` to input ``port`` of the unit, as an upstream unit would."""
        source = self._sources.get(port)
        if source is None:
            raise LibraryError(f"no input port {port!r}", where=f"transformation {self.spec.label!r}", expected=_ports(self._sources))
        source.emit(payload, origin_ns=origin_ns)

    def received(self, port: str) -> list[Message]:
        """What output ``port`` has published so far."""
        return list(self._sink(port).messages)

    def wait_for(self, port: str, count: int, timeout_s: float = 5.0) -> list[Message]:
        """Wait until output ``port`` has published ``count`` messages; returns them all (TimeoutError if not)."""
        return self._sink(port).wait_for(count, timeout_s)

    def wait_until(self, port: str, predicate: Callable[[Message], bool], timeout_s: float = 5.0) -> Message:
        """Wait for a message from output ``port``, from now on, that satisfies ``predicate``."""
        return self._sink(port).wait_until(predicate, timeout_s)

    def _sink(self, port: str) -> Sink:
        sink = self._sinks.get(port)
        if sink is None:
            raise LibraryError(f"no output port {port!r}", where=f"transformation {self.spec.label!r}", expected=_ports(self._sinks))
        return sink


def _ports(ports: Mapping[str, object]) -> str:
    return "one of " + ", ".join(repr(p) for p in ports) if ports else "none: the unit has no such ports"


def _unit_as(unit: Unit, cls: type[Any]) -> Any:
    assert isinstance(unit, cls), f"expected a {cls.__name__}, got {type(unit).__name__}"
    return unit


def _choose(spec: TransformationSpec | str | os.PathLike[str], label: str | None, ontology: Ontology | None) -> TransformationSpec:
    if isinstance(spec, TransformationSpec):
        return spec
    individuals = ontology.individuals if ontology is not None else None
    text = os.fspath(spec)
    if isinstance(spec, str) and text.lstrip().startswith("<"):
        specs = parse_specs(text, "<UnitHarness>", individuals=individuals)
    else:
        specs = load_specs([Path(text)], individuals=individuals)
    labels = [s.label for s in specs]
    if label is None:
        if len(specs) != 1:
            raise LibraryError(
                f"{len(specs)} transformations to choose from", where=text[:80], expected=f"label= one of {', '.join(map(repr, labels))}"
            )
        return specs[0]
    for candidate in specs:
        if candidate.label == label:
            return candidate
    raise LibraryError(f"no transformation labelled {label!r}", where=text[:80], expected=f"one of {', '.join(map(repr, labels))}")
