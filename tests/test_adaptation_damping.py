"""Flap damping (issue 54, item 9): a penalty per relapse that decays with a half-life, as
route-flap damping does; checked against a naive simulation that decays the penalty in 1 ms steps
and follows the suppress and reuse thresholds as RFC 2439 states them, and through the knowledge of
the loop for each kind of relapse (failures, managers lost again). A provider that relapses after
every start, with real managers: tests/test_adaptation_requirements.py; a link that flaps:
tests/test_hosts.py."""

from __future__ import annotations

import math
import random

import pytest

from dyknow.adaptation import FAILURES, LINKS, TRIALS, Damping, Flaps, Knowledge
from dyknow.adaptation.damping import Penalty

MS = 1_000_000


def _naive(damping: Damping, relapses: list[int], steps: int, step_s: float) -> list[tuple[float, bool]]:
    """The penalty and whether it is suppressed at each step: decayed by 2**(-step / half life)
    each step, a relapse adds the penalty (at most the ceiling); suppressed when above the
    suppress threshold, until it is at or below the reuse threshold."""
    step = 0.5 ** (step_s / damping.half_life_s)
    value, suppressed, out = 0.0, False, []
    at = set(relapses)
    for t in range(steps):
        if t:
            value *= step
        if suppressed and value <= damping.reuse:
            suppressed = False
        if t in at:
            value = min(damping.ceiling, value + damping.penalty)
            suppressed = suppressed or value > damping.suppress
        out.append((value, suppressed))
    return out


@pytest.mark.parametrize("damping", [TRIALS, LINKS, Damping(half_life_s=2.0, suppress=1500.0, reuse=300.0, max_hold_s=5.0)], ids=["trials", "links", "short"])
def test_the_penalty_equals_a_naive_simulation(damping: Damping) -> None:
    """Random relapses, some close together (suppressed), some far apart (forgiven): at every
    step (a thousandth of the half-life) the penalty and whether it is suppressed equal the naive
    simulation's (a step's slack where the penalty crosses the reuse threshold)."""
    rng = random.Random(54)
    step_s = damping.half_life_s / 1000
    step_ns = round(step_s * 1e9)
    span = 8000  # 8 half-lives
    for _ in range(6):
        relapses = sorted({rng.randrange(span) for _ in range(rng.randrange(2, 9))})
        if rng.random() < 0.5:  # a burst
            relapses = sorted({*relapses, *(relapses[0] + i * rng.randrange(1, 300) for i in range(5))})
        expected = _naive(damping, relapses, span + round(damping.max_hold_s / step_s) + 10, step_s)
        penalty = Penalty(damping)
        pending = list(relapses)
        crossed = 0
        for t, (value, suppressed) in enumerate(expected):
            now = t * step_ns
            if pending and pending[0] == t:
                penalty.relapse(now)
                pending.pop(0)
            assert math.isclose(penalty.value(now), value, rel_tol=1e-6), (relapses, t)
            ours = penalty.suppressed and now < penalty.suppressed_until()
            if ours != suppressed:  # only where it crosses the reuse threshold, within a step
                assert abs(penalty.suppressed_until() - now) <= step_ns, (relapses, t, value)
                crossed += 1
        assert penalty.relapses == len(relapses) and crossed <= len(relapses)


def test_one_relapse_suppresses_nothing_and_the_hold_never_exceeds_its_longest() -> None:
    """A single relapse leaves a penalty under every kind's suppress threshold; however many come
    at once, the suppression lasts at most ``max_hold_s`` after the last."""
    for damping in (TRIALS, LINKS):
        once = Penalty(damping)
        once.relapse(0)
        assert not once.suppressed and once.suppressed_until() == 0
        many = Penalty(damping)
        for i in range(50):
            many.relapse(i * MS)
        assert many.suppressed and many.suppressed_until() - 49 * MS == pytest.approx(damping.max_hold_s * 1e9, rel=1e-9)


def test_figures_that_cannot_work_are_refused() -> None:
    with pytest.raises(ValueError, match="reuse < suppress"):
        Damping(half_life_s=10.0, suppress=400.0, reuse=500.0, max_hold_s=30.0)
    with pytest.raises(ValueError, match=r"the ceiling reuse \* 2 \*\* \(max_hold_s / half_life_s\) = 500"):
        Damping(half_life_s=10.0, suppress=1500.0, reuse=250.0, max_hold_s=10.0)  # never suppressed
    with pytest.raises(ValueError, match="half_life_s > 0"):
        Damping(half_life_s=0.0, suppress=1500.0, reuse=250.0, max_hold_s=10.0)


def test_the_target_a_provider_that_fails_8_s_after_every_start_switches_at_most_3_times_in_10_minutes() -> None:
    """With the default figures (TRIALS) and the loop's times (trial after 1 s, held for the dwell
    time, 2 s): the provider's relapses and the request's switches, stepped through by hand. Its
    first relapse (8 s) moves the request away; its trial at 9 s holds at 11 s (back); it relapses
    at 17 s (8 s after the trial started: away): suppressed for about 15 minutes, so 3 switches in
    the first 10 minutes; later, at most one return in any 10 minutes."""
    dwell, fail_after, backoff = 2.0, 8.0, 1.0
    penalty = Penalty(TRIALS)
    switches: list[float] = []
    t = fail_after  # its first relapse
    while t < 3600:
        penalty.relapse(int(t * 1e9))
        switches.append(t)  # away
        trial = max(t + backoff, penalty.suppressed_until() / 1e9 if penalty.suppressed else 0.0)
        switches.append(trial + dwell)  # back, once its trial held for the dwell time
        t = trial + fail_after  # the unit the trial started relapses
    assert switches[:3] == [8.0, 11.0, 17.0] and switches[3] > 600  # at most 3 in the first 10 minutes
    for i, at in enumerate(switches):
        assert len([s for s in switches[i:] if s < at + 600]) <= 3, switches  # in any 10 minutes


def test_a_transformation_that_fails_again_and_again_waits_longer_and_is_forgiven_as_it_stops() -> None:
    """Failures close together double the back-off (1, 2, 4 ... at most 60 s); an hour later, the
    back-off is 1 s again (before, it stayed at 60 s for ever)."""
    knowledge = Knowledge()
    waits = []
    for i in range(9):
        knowledge.fail("camera", i * 100 * MS)
        waits.append(knowledge.backoff["camera"][1])
    assert waits == [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 60.0, 60.0, 60.0]
    knowledge.fail("camera", 3600 * 10**9)
    assert knowledge.backoff["camera"][1] == 1.0
    knowledge.fail("camera", 3601 * 10**9)
    assert knowledge.backoff["camera"][1] == 2.0
    assert FAILURES.ceiling > 7 * FAILURES.penalty  # the 60 s cap is reached before the ceiling


def test_a_manager_lost_again_soon_is_held_back_until_its_penalty_decays() -> None:
    """Back from one loss, a manager is on probation for the dwell time. Lost again 4 s after the
    first loss, its penalty (1000 * 2**(-4/10) + 1000 = 1758) is above the suppress threshold: on
    probation until it decays to 250 (10 s * log2(1758 / 250) = 28.1 s after that loss), however
    soon it is back. Lost again much later, only the dwell time again."""
    dwell = 500 * MS
    knowledge = Knowledge()
    knowledge.lost("robot", 0)
    knowledge.found("robot", 1000 * MS)
    until, penalty = knowledge.probation("robot", 1000 * MS, dwell)
    assert until == 1500 * MS and penalty is not None and penalty.relapses == 1
    knowledge.lost("robot", 4000 * MS)
    knowledge.found("robot", 5000 * MS)
    until, _ = knowledge.probation("robot", 5000 * MS, dwell)
    assert abs(until - 4000 * MS - 28.1 * 1e9) < 0.05 * 1e9
    assert knowledge.on_probation(31_000 * MS, dwell) == {"robot"} and knowledge.on_probation(32_200 * MS, dwell) == set()
    knowledge.lost("robot", 200_000 * MS)  # long after: its penalty decayed to almost nothing
    knowledge.found("robot", 201_000 * MS)
    assert knowledge.probation("robot", 201_000 * MS, dwell)[0] == 201_500 * MS


def test_the_figures_are_a_managers_to_choose() -> None:
    quick = Flaps(links=Damping(half_life_s=1.0, suppress=1200.0, reuse=250.0, max_hold_s=3.0))
    knowledge = Knowledge(quick)
    knowledge.lost("robot", 0)
    knowledge.lost("robot", 500 * MS)
    knowledge.found("robot", 600 * MS)
    until, _ = knowledge.probation("robot", 600 * MS, 100 * MS)
    assert 3.2e9 < until < 3.35e9  # 1 s * log2(1707 / 250) = 2.77 s after the second loss
