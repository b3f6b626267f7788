"""Smoke runs of benchmarks/peers.py: each peer's chain runs here and keeps its contract (no timing asserts)."""

from __future__ import annotations

import importlib
import math
import sys
from collections.abc import Iterator
from types import ModuleType

import pytest

from tests.conftest import REPO, dds_domain

VARIANTS = ("dds-process", "dora-process", "zmq-process")


@pytest.fixture(scope="module")
def peers() -> Iterator[ModuleType]:
    """benchmarks/peers.py, imported as chain.py imports it (its folder on the path, for ``harness``)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.syspath_prepend(str(REPO / "benchmarks"))
        yield importlib.import_module("peers")
    sys.modules.pop("peers", None)


def test_every_peer_can_run_here(peers: ModuleType) -> None:
    # the test extra installs the bench extra: in CI the peers are measured, never skipped
    assert peers.PEER_VARIANTS == VARIANTS
    assert {variant: peers.missing(variant) for variant in VARIANTS} == dict.fromkeys(VARIANTS)


def test_an_unknown_peer_is_refused_with_the_known_ones(peers: ModuleType) -> None:
    with pytest.raises(ValueError, match="unknown peer 'ros2'; expected one of dds-process, dora-process, zmq-process"):
        peers.missing("ros2")


@pytest.mark.process
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize(("total", "rate_hz"), [(20, None), (10, 200.0)], ids=["back-to-back", "paced"])
def test_peer_chain_delivers_every_message(peers: ModuleType, variant: str, total: int, rate_hz: float | None) -> None:
    # a DDS domain of this test's own: a parallel worker's DDS test never joins it
    # (the sink waits 30 s for a message, not the benchmark's 3: beside CPU hogs a process of the chain stalls seconds)
    latencies, cpu_s_per_message = peers.run_peer(variant, hops=2, total=total, rate_hz=rate_hz, domain=dds_domain(), idle_s=30.0)
    assert len(latencies) == total
    assert all(isinstance(ns, int) and ns > 0 for ns in latencies)
    assert math.isfinite(cpu_s_per_message) and cpu_s_per_message >= 0
