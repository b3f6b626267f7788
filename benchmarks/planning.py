"""Planning time on libraries of 100, 1,000 and 10,000 transformation specs.

Each library is a seeded random layered graph, like a large robot's: ``layers`` layers of specs;
a spec consumes one or two tags of the layer below and provides one tag of its layer, and every
tag has several providers (alternatives with different priorities), a few of them unavailable or
constrained by a measurement. Tags of half the specs use classes of the project ontology with
subclass matching; the rest are functors in no ontology. Requests ask for tags of the top layer.

Reports the time to index a library (building a :class:`Planner`, once per library version) and
the time of one plan, median and p99: *cold* (the first plan of a request, which also builds the
request's graph) and *warm* (later plans of the same request under other conditions, as when
adapting), beside the target (under 10 ms for 1,000 specs, checked on the cold p99).

    python benchmarks/planning.py --json out/planning.json
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dyknow import Ontology, Planner, PlanningError, TransformationSpec
from dyknow.resources import specs_dir
from dyknow.spec import Constraint, Port, Tag

from harness import machine, write_json

TARGET_MS = {1000: 10.0}
LAYERS = 8
# ontology classes with subclass chains, used for half the tags: Image <- RawImage <- YUVImage ...
ONTOLOGY_FUNCTORS = ["RawImage", "YUVImage", "HSVImage", "BallObject", "WorldObject", "BallPosition", "BallTrack", "Image"]


def library(size: int, seed: int = 7) -> list[TransformationSpec]:
    """A seeded random library of ``size`` specs in ``LAYERS`` layers (see the module documentation)."""
    rng = random.Random(seed)
    per_layer = max(2, size // LAYERS)
    tags_per_layer = max(1, per_layer // 3)  # about three providers per tag

    def tag(layer: int, i: int) -> str:
        functor = ONTOLOGY_FUNCTORS[(layer + i) % len(ONTOLOGY_FUNCTORS)] if (layer + i) % 2 else f"T{layer}"
        return f"{functor}(a{layer}_{i})"

    specs = []
    for n in range(size):
        layer = n % LAYERS
        out = tag(layer, rng.randrange(tags_per_layer))
        ports = [Port("out", "out")]
        tags = [Tag("out", out)]
        if layer > 0:
            for k in range(rng.choice((1, 1, 2))):
                ports.append(Port(f"in{k}", "in"))
                tags.append(Tag(f"in{k}", tag(layer - 1, rng.randrange(tags_per_layer))))
        constraints = (Constraint("battery", ">=", 0.5),) if rng.random() < 0.05 else ()
        specs.append(
            TransformationSpec(
                label=f"t{n:05d}", source="m:C", ports=tuple(ports), tags=tuple(tags),
                priority=rng.randrange(1, 200), constraints=constraints,
            )  # fmt: skip
        )
    return specs


def main(argv: list[str] | None = None) -> int:
    """Time indexing and planning on each library size, print a table (and write JSON with ``--json``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="100,1000,10000")
    parser.add_argument("--requests", type=int, default=200, help="plans per library")
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    sizes = [int(s) for s in ("100,1000" if args.smoke else args.sizes).split(",")]
    count = 20 if args.smoke else args.requests
    info = machine()
    print(f"machine: {info['cpu']}, {info['cores']} cores, Python {info['python']}")
    ontology = Ontology.load([specs_dir() / "dyknow.ttl"])
    results: list[dict[str, Any]] = []
    print(f"{'specs':>6} {'index':>10} {'cold p50':>10} {'cold p99':>10} {'warm p50':>10} {'warm p99':>10} {'ok/fail':>9} target")
    for size in sizes:
        specs = library(size)
        t0 = time.perf_counter()
        planner = Planner(specs, ontology)
        index_ms = (time.perf_counter() - t0) * 1000
        top = LAYERS - 1
        wanted = sorted({t.tag for s in specs for t in s.tags if t.port == "out" and s.label and int(s.label[1:]) % LAYERS == top})
        rng = random.Random(size)
        cold, warm, ok, failed = [], [], 0, 0
        seen: set[str] = set()
        for _ in range(count):
            request = wanted[rng.randrange(len(wanted))]
            unavailable = {f"t{rng.randrange(size):05d}" for _ in range(size // 50)}
            t0 = time.perf_counter()
            try:
                planner.plan(request, unavailable=unavailable, measurements={"battery": rng.random()})
                ok += 1
            except PlanningError:
                failed += 1  # an explanation is a result too: it is timed the same way
            (warm if request in seen else cold).append((time.perf_counter() - t0) * 1000)
            seen.add(request)

        def pct(values: list[float], q: float) -> float:
            return round(float(np.percentile(np.asarray(values), q)), 3) if values else float("nan")

        row = {
            "specs": size,
            "index_ms": round(index_ms, 2),
            "cold_median_ms": pct(cold, 50),
            "cold_p99_ms": pct(cold, 99),
            "warm_median_ms": pct(warm, 50),
            "warm_p99_ms": pct(warm, 99),
            "requests": len(cold),
            "planned": ok,
            "failed": failed,
        }
        results.append(row)
        target = TARGET_MS.get(size)
        note = f"< {target:g} ms per plan: {'met' if row['cold_p99_ms'] < target else 'MISSED'} (cold p99)" if target else ""
        print(
            f"{size:>6} {index_ms:>8.1f}ms {row['cold_median_ms']:>8.3f}ms {row['cold_p99_ms']:>8.3f}ms "
            f"{row['warm_median_ms']:>8.3f}ms {row['warm_p99_ms']:>8.3f}ms {ok:>5}/{failed:<3} {note}",
            flush=True,
        )
    if args.json:
        write_json(args.json, {"machine": info, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
