"""dyknow.testing: what users test their own units with."""

from __future__ import annotations

import pytest

from dyknow import LibraryError, Message, Unit, UnitError
from dyknow.testing import Sink, UnitHarness
from tests.conftest import REPO

DOUBLER = """<transformation>
  <label>doubler</label>
  <source>tests.test_testing:Doubler</source>
  <params><param name="factor" type="int">2</param></params>
  <ports><port type="in">in</port><port type="out">out</port><port type="out">count</port></ports>
</transformation>"""


class Doubler(Unit):
    """The first tutorial's example unit (docs/tutorials/first-unit.md), plus a count of what it saw."""

    def setup(self) -> None:
        self.seen = 0

    def on_message(self, port: str, msg: Message) -> None:
        self.seen += 1
        self.publish("out", msg.payload * self.params["factor"])
        self.publish("count", self.seen)


def test_a_unit_test_is_ten_lines() -> None:
    with UnitHarness(DOUBLER, params={"factor": 3}) as harness:
        harness.send("in", 2)
        harness.send("in", 5, origin_ns=1234)
        out = harness.wait_for("out", 2)
        assert [m.payload for m in out] == [6, 15]
        assert out[1].origin_ns == 1234  # the origin travels through the unit
        assert [m.payload for m in harness.wait_for("count", 2)] == [1, 2]
        harness.send("in", 1)
        assert harness.wait_until("count", lambda m: m.payload > 2).payload == 3  # from now on
        assert isinstance(harness.unit, Doubler) and harness.unit.seen == 3
        assert harness.info.state == "running"
        assert harness.statistics().ports[0].messages == 3


def test_a_spec_file_with_several_transformations_needs_a_label() -> None:
    generic = REPO / "specs" / "generic.xml"
    with pytest.raises(LibraryError, match="transformations to choose from; expected label= one of 'periodic-source'"):
        UnitHarness(generic)
    with pytest.raises(LibraryError, match="no transformation labelled 'relai'; expected one of"):
        UnitHarness(generic, "relay".replace("y", "i"))
    with UnitHarness(generic, "relay") as harness:
        harness.send("in", b"abc")
        assert harness.wait_for("out", 1)[0].payload == b"abc"


def test_unknown_ports_are_clear_errors() -> None:
    with UnitHarness(DOUBLER) as harness:
        with pytest.raises(LibraryError, match="no input port 'inn'; expected one of 'in'"):
            harness.send("inn", 1)
        with pytest.raises(LibraryError, match="no output port 'in'; expected one of 'out', 'count'"):
            harness.received("in")


def test_a_unit_failing_in_setup_shows_in_the_model() -> None:
    with UnitHarness(REPO / "tests" / "units.xml", "setup-fails") as harness:
        assert harness.info.state == "failed"
        assert harness.info.error == "setup(): ValueError: cannot open the device"


def test_a_unit_no_manager_runs_says_how_to_run_it() -> None:
    sink = Sink()
    with pytest.raises(UnitError, match="the unit is not running, so it cannot publish; expected a unit spawned by a Manager"):
        sink.publish("out", 1)
    with pytest.raises(UnitError, match="cannot create timer"):
        sink.create_timer(1.0, lambda: None)
