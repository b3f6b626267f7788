"""The local bus: who delivers to whom, wildcards, atomic rebinding."""

from __future__ import annotations

import pytest

from dyknow.bus import LocalBus
from dyknow.errors import BindingError


class Job:
    def __init__(self, name: str) -> None:
        self.name = name


class Out:
    def __init__(self, key: str, name: str = "out") -> None:
        self.key = key
        self.name = name
        self.targets: tuple[In, ...] = ()


class In:
    """An input port; ``forward``: the output its (forwarding) unit passes every message to."""

    def __init__(self, key: str, name: str = "in", unit: str = "u", forward: Out | None = None) -> None:
        self.key = key
        self.name = name
        self.job = Job(unit)
        self.forward = forward


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


# ---------------------------------------------------------------------------- forwarding cycles


def _relay(unit: str, in_key: str, out_key: str) -> tuple[In, Out]:
    out = Out(out_key)
    return In(in_key, unit=unit, forward=out), out


def test_forwarding_units_that_would_close_a_cycle_are_refused_naming_the_ports() -> None:
    bus = LocalBus()
    a_in, a_out = _relay("a", "x/b", "x/a")
    b_in, b_out = _relay("b", "x/a", "x/b")
    bus.attach([], [a_out])
    bus.attach([a_in], [])
    bus.attach([], [b_out])
    assert bus.forwarding_cycle(inputs=[b_in]) == [(b_in, b_out), (a_in, a_out)]
    with pytest.raises(BindingError) as refused:
        bus.attach([b_in], [])
    assert "b.in (x/a) -> b.out (x/b) -> a.in (x/b) -> a.out (x/a) -> b.in" in str(refused.value)
    assert b_out.targets == (a_in,) and a_out.targets == (), "nothing was attached"
    assert len(bus) == 3


def test_a_forwarding_unit_reading_its_own_output_through_a_wildcard_is_refused() -> None:
    bus = LocalBus()
    r_in, r_out = _relay("r", "dyknow/**", "dyknow/m/r/out")
    bus.attach([], [r_out])
    with pytest.raises(BindingError, match=r"r\.in \(dyknow/\*\*\) -> r\.out \(dyknow/m/r/out\) -> r\.in"):
        bus.attach([r_in], [])


def test_a_rebinding_that_closes_a_cycle_changes_nothing() -> None:
    bus = LocalBus()
    a_in, a_out = _relay("a", "x/0", "x/a")
    b_in, b_out = _relay("b", "x/a", "x/b")
    c_in, c_out = _relay("c", "x/b", "x/c")
    for inp, out in ((a_in, a_out), (b_in, b_out), (c_in, c_out)):
        bus.attach([], [out])
        bus.attach([inp], [])
    with pytest.raises(BindingError, match=r"a\.in \(x/c\) -> a\.out \(x/a\) -> b\.in"):
        bus.rebind([(a_in, "x/c")])  # the new key is the one shown
    assert a_in.key == "x/0" and c_out.targets == ()
    with pytest.raises(BindingError, match="cycle"):
        bus.rebind([(c_out, "x/0")])  # c's output moved onto the key a reads
    assert c_out.key == "x/c" and c_out.targets == ()
    assert bus.forwarding_cycle(changes=[(a_in, "x/*")]) is not None  # reading x/* takes x/c too
    bus.rebind([(a_in, "y/*")])
    assert a_in.key == "y/*"


def test_cycles_through_units_that_run_python_are_allowed() -> None:
    """A unit without forward_to decides itself what to publish: a feedback loop may be meant."""
    bus = LocalBus()
    a_in, a_out = _relay("a", "x/b", "x/a")
    b_out = Out("x/b")
    b_in = In("x/a", unit="b")  # runs Python
    bus.attach([a_in], [a_out])
    bus.attach([b_in], [b_out])
    assert a_out.targets == (b_in,) and b_out.targets == (a_in,)


def test_cycle_verdicts_match_a_naive_closure_over_zenoh_key_expressions() -> None:
    """Random systems of forwarding and plain units, attached one at a time: the bus refuses
    exactly the attachments after which a naive transitive closure (every pair compared with
    Zenoh's own KeyExpr.intersects) finds a forwarding input that reaches itself."""
    import random

    import zenoh

    keys = ["k/a", "k/b", "k/c", "k/*", "k/**", "**", "j/a", "j/*", "k/a/b", "*/a"]

    def naive_cycle(inputs: list[In]) -> bool:
        forwarding = [p for p in inputs if p.forward is not None]
        reach = {
            (i, j): zenoh.KeyExpr(p.forward.key).intersects(zenoh.KeyExpr(q.key))  # type: ignore[union-attr]
            for i, p in enumerate(forwarding)
            for j, q in enumerate(forwarding)
        }
        n = len(forwarding)
        for k in range(n):
            for i in range(n):
                for j in range(n):
                    if reach[i, k] and reach[k, j]:
                        reach[i, j] = True
        return any(reach[i, i] for i in range(n))

    rng = random.Random(20261125)
    refusals = 0
    for _ in range(300):
        bus = LocalBus()
        attached: list[In] = []
        for u in range(rng.randint(1, 5)):
            out = Out(rng.choice([k for k in keys if "*" not in k]))
            inp = In(rng.choice(keys), unit=f"u{u}", forward=out if rng.random() < 0.7 else None)
            bus.attach([], [out])
            expect_refusal = naive_cycle([*attached, inp])
            try:
                bus.attach([inp], [])
            except BindingError:
                assert expect_refusal, f"refused without a cycle: {[(p.key, p.forward and p.forward.key) for p in attached]} + {inp.key}"
                refusals += 1
                continue
            assert not expect_refusal, f"missed a cycle: {[(p.key, p.forward and p.forward.key) for p in [*attached, inp]]}"
            attached.append(inp)
    assert refusals > 20  # the draw does exercise refusals
