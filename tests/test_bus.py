"""The local bus: who delivers to whom, wildcards, atomic rebinding."""

from __future__ import annotations

from dyknow.bus import LocalBus


class In:
    def __init__(self, key: str) -> None:
        self.key = key


class Out:
    def __init__(self, key: str) -> None:
        self.key = key
        self.targets: tuple[In, ...] = ()


def test_routes_follow_keys_and_wildcards() -> None:
    bus = LocalBus()
    exact, star, deep, other = In("r/cam/image"), In("r/*/image"), In("r/**"), In("x/y")
    out = Out("r/cam/image")
    bus.attach([exact, star], [out])
    assert out.targets == (exact, star)
    bus.attach([deep, other], [])
    assert out.targets == (exact, star, deep)
    late = Out("r/lidar/scan")
    bus.attach([], [late])
    assert late.targets == (deep,)


def test_rebind_moves_inputs_and_outputs_at_once() -> None:
    bus = LocalBus()
    a, b = In("k/a"), In("k/b")
    out1, out2 = Out("k/a"), Out("k/b")
    bus.attach([a, b], [out1, out2])
    assert (out1.targets, out2.targets) == ((a,), (b,))
    bus.rebind([(a, "k/b"), (out1, "k/z")])
    assert out1.targets == ()
    assert set(out2.targets) == {a, b}
    bus.rebind([(out1, "k/b")])
    assert set(out1.targets) == {a, b}


def test_detach_stops_delivery() -> None:
    bus = LocalBus()
    a = In("k")
    out = Out("k")
    bus.attach([a], [out])
    bus.detach([a], [])
    assert out.targets == ()
    bus.detach([], [out])
    bus.attach([In("k")], [])
    assert out.targets == ()  # a detached output is not routed again
