"""Testing units: stand-in units, the paper's scenario and a harness, so a unit test is ten lines.

What users need to test their own units (as ``bytewax.testing`` ships with bytewax):

- :class:`UnitHarness` runs one unit from its spec in a private manager: ``send(port, payload)``
  feeds an input, ``wait_for(port, n)`` returns what an output published;
- :class:`Sink` records what arrives (``wait_for(count)``, ``wait_until(predicate)``) and
  :class:`Source` publishes what the test hands it (``emit(payload)``), to wire by hand in a
  manager of your own;
- :data:`SCENARIO_SPECS` and its units (:class:`Camera`, :class:`Subsampler`, :class:`Detector`,
  :class:`Localization`, :class:`Tracker`): the DyKnow paper's ball-tracking scenario without
  OpenCV, for tests of planning and self-adaptation; :data:`SCENARIO_HOSTS`: the same specs
  split over three managers (robot, field, station);
- :mod:`dyknow.testing.fuzzing` (imported on its own; it needs Hypothesis, a test dependency):
  strategies for spec documents, tags, service requests and damaged MCAP files, and the
  properties dyknow keeps for any of them, shared by the fuzz tests and ``tools/fuzz.py``;
- :mod:`dyknow.testing.bombs` (imported on its own): MCAP decompression bombs built in a moment
  (a chunk of 33 KB holding 1 GiB, chunks whose sizes lie, overlapping chunks), for the tests of
  anything that reads MCAP files and for ``benchmarks/mcap_bombs.py``.
- :mod:`dyknow.testing.memory` (imported on its own): :func:`~dyknow.testing.memory.peak_run`,
  the peak memory of a command alone (``ru_maxrss`` of a child counts its parent's size too).

Example::

    from dyknow.testing import UnitHarness

    def test_doubler():
        with UnitHarness("specs/doubler.xml", "doubler", params={"factor": 3}) as harness:
            harness.send("in", 2)
            assert harness.wait_for("out", 1)[0].payload == 6

Units here are named in specs as ``dyknow.testing:Sink`` and so on.
"""

from __future__ import annotations

from dyknow.testing.harness import UnitHarness
from dyknow.testing.scenario import CAMERA_IDS, SCENARIO_HOSTS, SCENARIO_SPECS, Camera, Detector, Localization, Subsampler, Tracker
from dyknow.testing.units import Sink, Source

__all__ = [
    "CAMERA_IDS",
    "SCENARIO_HOSTS",
    "SCENARIO_SPECS",
    "Camera",
    "Detector",
    "Localization",
    "Sink",
    "Source",
    "Subsampler",
    "Tracker",
    "UnitHarness",
]
