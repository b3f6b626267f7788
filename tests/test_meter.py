"""dyknow.meter: a stream's rate, jitter and sizes, checked against the statistics module."""

from __future__ import annotations

import json
import random
import statistics
from collections.abc import Callable

import pytest

from dyknow.meter import StreamMeter
from tests.conftest import ManagerProcess, run_cli


def test_the_figures_are_those_of_the_last_window() -> None:
    rng = random.Random(7)
    meter = StreamMeter(window=50)
    t, arrivals = 0, []
    for _ in range(80):
        t += 20_000_000 + rng.randrange(-2_000_000, 2_000_000)  # 50 Hz, +/- 2 ms
        size = rng.randrange(10, 1000)
        arrivals.append((t, size))
        meter.add("a/b", size, now_ns=t)
    (f,) = meter.figures(now_ns=t + 5_000_000)
    last = arrivals[-50:]
    intervals = [(b[0] - a[0]) / 1e6 for a, b in zip(last, last[1:], strict=False)]
    assert f.messages == 80 and f.window == 50
    assert f.rate_hz == pytest.approx(49 / ((last[-1][0] - last[0][0]) / 1e9))
    assert f.interval_mean_ms == pytest.approx(statistics.fmean(intervals))
    assert f.jitter_ms == pytest.approx(statistics.pstdev(intervals))
    assert (f.interval_min_ms, f.interval_max_ms) == (pytest.approx(min(intervals)), pytest.approx(max(intervals)))
    assert f.size_mean_b == pytest.approx(statistics.fmean(s for _, s in last))
    assert (f.size_min_b, f.size_max_b) == (min(s for _, s in last), max(s for _, s in last))
    assert f.bandwidth_bps == pytest.approx(sum(s for _, s in last[1:]) / ((last[-1][0] - last[0][0]) / 1e9))
    assert f.idle_s == pytest.approx(0.005)
    assert json.loads(json.dumps(f.to_dict()))["interval_ms"]["std"] == round(f.jitter_ms, 3)


def test_keys_are_apart_and_one_message_gives_no_figures() -> None:
    meter = StreamMeter(window=10)
    meter.add("a", 1, now_ns=0)
    assert meter.figures(now_ns=1) == [] and meter.counts() == {"a": 1}
    for i in range(1, 4):
        meter.add("a", 1, now_ns=i * 100_000_000)
        meter.add("b", 2, now_ns=i * 50_000_000)
    assert [(f.key, round(f.rate_hz)) for f in meter.figures(now_ns=10**9)] == [("a", 10), ("b", 20)]
    with pytest.raises(ValueError, match="at least 2"):
        StreamMeter(window=1)


@pytest.mark.process
def test_hz_measures_a_source_as_an_operator_would(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process()
    assert run_cli("spawn", "periodic-source", "src", "--param", "rate_hz=50", "--param", "payload_size=100", *proc.client_args()).returncode == 0
    done = run_cli("hz", f"dyknow/{proc.name}/src/out", "--duration", "2.5", "--every", "1", "--json", *proc.client_args())
    assert done.returncode == 0, done.stderr
    last = json.loads(done.stdout.splitlines()[-1])
    assert last["key"] == f"dyknow/{proc.name}/src/out" and 30 < last["rate_hz"] < 70  # 50 Hz, as delivered here
    assert last["size_bytes"]["min"] >= 100  # the payload, and the header beside it
    quiet = run_cli("hz", "nothing/here", "--duration", "0.5", *proc.client_args())
    assert quiet.returncode == 1 and "no message on 'nothing/here'" in quiet.stderr


@pytest.mark.process
def test_top_shows_every_unit_with_its_rates(manager_process: Callable[..., ManagerProcess]) -> None:
    proc = manager_process()
    client = proc.client_args()
    assert run_cli("spawn", "periodic-source", "src", "--param", "rate_hz=50", *client).returncode == 0
    assert run_cli("spawn", "relay", "r1", "--bind", f"in=dyknow/{proc.name}/src/out", *client).returncode == 0
    done = run_cli("top", "--once", "--json", "--interval", "1", *client)
    assert done.returncode == 0, done.stderr
    (view,) = json.loads(done.stdout)["managers"]
    units = {u["name"]: u for u in view["units"]}
    assert view["manager"] == proc.name and view["cpu_pct"] is not None and set(units) == {"src", "r1"}
    assert 25 < units["r1"]["in_hz"] < 100 and 25 < units["src"]["out_hz"] < 100 and units["r1"]["hop_p50_us"] is not None
    text = run_cli("top", "--once", "--interval", "0.5", *client).stdout
    assert f"manager {proc.name}: cpu" in text and "UNIT" in text and "r1" in text and "relay" in text
