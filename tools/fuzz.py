"""Fuzz dyknow's inputs for minutes, randomized, before a release; print what each target found.

    python tools/fuzz.py --minutes 10 [--targets spec,tags,request,service,mcap] [--data DIR] [--json]

The same properties as the test suite's ``tests/test_fuzz_*.py`` (they live in
:mod:`dyknow.testing.fuzzing`), but randomized (new examples every run) and for as long as asked;
the time is shared equally among the targets:

- ``spec``: generated spec documents and the repository's ``specs/*.xml`` mutated: they parse and
  round-trip, or raise a SpecError located in them;
- ``tags``: generated and arbitrary tag text: a term that round-trips, or a TagError;
- ``request``: any payload to any service, checked directly: its fields, or a DyKnowError;
- ``service``: the same over Zenoh to a manager started here (loopback only): a reply or an error
  reply naming a DyKnowError class, and the manager answers ``get_model`` after each;
- ``mcap``: our writer's recordings and the data folder's (``$DYKNOW_DATA``, default
  ``../shared/data`` next to the repository; our own only when it is missing) truncated,
  bit-flipped and with bad length fields: read, or a RecordingError, within a time bound.

Prints one line per target: the examples tried (shrinking included) and, for a failure, the
minimal failing example Hypothesis found and the error (``--json``: one JSON object per target,
``{"target", "examples", "elapsed_s", "ok", "failure"}``). Exit status 0 when no target failed,
1 when one did, 2 for bad arguments. Needs Hypothesis (``pip install 'dyknow[test]'``). Logging
below CRITICAL is silenced: damaged files are expected to make the reader warn.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from a checkout without installing

from dyknow import Client, Manager
from dyknow.testing import SCENARIO_SPECS
from dyknow.testing.fuzzing import (
    TARGETS,
    Outcome,
    Property,
    mcap_property,
    request_property,
    run_for,
    service_property,
    spec_property,
    tag_property,
    write_seed_recordings,
)

TOOLS = Path(__file__).resolve().parent
REPO = TOOLS.parent


def spec_seeds() -> dict[str, bytes]:
    """The documents the ``spec`` target mutates: the repository's specs and the package's scenario specs."""
    paths = [*sorted((REPO / "specs").glob("*.xml")), *sorted(SCENARIO_SPECS.parent.glob("*.xml"))]
    return {path.name: path.read_bytes() for path in paths}


def mcap_seeds(data: Path, folder: Path) -> dict[str, Path]:
    """The recordings the ``mcap`` target mutates: our writer's (written to ``folder``), the
    repository's Foxglove file, and the data folder's real files and conformance variants."""
    paths = [*write_seed_recordings(folder), REPO / "tests" / "mcap" / "foxglove-protobuf.mcap"]
    paths += sorted((data / "mcap" / "real").glob("*.mcap"))
    conformance = data / "mcap" / "conformance"
    for base in sorted(conformance.iterdir()) if conformance.is_dir() else []:
        variants = sorted(base.glob("*.mcap"))
        if variants:  # the plain variant and the one with every feature
            paths += [variants[0], max(variants, key=lambda p: len(p.name))]
    return {path.name: path for path in paths}


@contextlib.contextmanager
def properties(target: str, data: Path, workdir: Path) -> Iterator[Property]:
    """The property of ``target``, with what it needs (a manager, seed files) for as long as it runs."""
    if target == "spec":
        yield spec_property(spec_seeds())
    elif target == "tags":
        yield tag_property()
    elif target == "request":
        yield request_property()
    elif target == "service":
        with Manager(f"fuzz{os.getpid()}", specs=[REPO / "specs" / "generic.xml"]) as manager:
            manager.spawn("relay", "s", protected=True)
            with Client(manager.name, connect=manager.endpoints) as client:
                yield service_property(client.session, manager.name, units=("s",))
    elif target == "mcap":
        if not (data / "mcap").is_dir():
            print(f"note: no MCAP data under {data}; the mcap target mutates our own recordings only", file=sys.stderr)
        yield mcap_property(mcap_seeds(data, workdir), workdir)
    else:
        raise ValueError(f"unknown target {target!r}")


def describe(outcome: Outcome) -> str:
    """The text report of one target: a line, and for a failure the example and error, indented."""
    line = f"{outcome.name:<8} {outcome.examples:>8} examples {outcome.elapsed_s:>8.1f} s  {'ok' if outcome.ok else 'FAILED'}"
    if outcome.failure is None:
        return line
    return line + "\n" + "\n".join(f"    {text}" for text in outcome.failure.splitlines())


def _targets(text: str) -> list[str]:
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in TARGETS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a comma-separated list of {', '.join(TARGETS)}")
    return names


def main(argv: Sequence[str] | None = None) -> int:
    """Run the chosen targets for the time given and print each outcome; 1 if a target failed."""
    parser = argparse.ArgumentParser(prog="fuzz.py", description=__doc__.splitlines()[0])
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=float, help="how long to fuzz, all targets together (default 1)")
    budget.add_argument("--seconds", type=float, help="the same in seconds")
    parser.add_argument("--targets", type=_targets, default=list(TARGETS), help=f"comma-separated, from {','.join(TARGETS)} (default all)")
    default = os.environ.get("DYKNOW_DATA", str(REPO.parent / "shared" / "data"))
    parser.add_argument("--data", type=Path, default=Path(default), help=f"the shared data folder (default $DYKNOW_DATA or {default})")
    parser.add_argument("--json", action="store_true", help="one JSON object per target instead of a line")
    args = parser.parse_args(argv)
    total_s = args.seconds if args.seconds is not None else 60.0 * (args.minutes if args.minutes is not None else 1.0)
    if not total_s >= 0:
        parser.error(f"--minutes/--seconds: got {total_s:g} s; expected 0 or more")

    logging.disable(logging.CRITICAL - 1)  # the refusals fuzzing provokes are logged: thousands of lines
    outcomes = []
    try:
        with tempfile.TemporaryDirectory(prefix="dyknow-fuzz-") as workdir:
            for target in args.targets:
                with properties(target, args.data, Path(workdir)) as prop:
                    outcome = run_for(prop, total_s / len(args.targets))
                outcomes.append(outcome)
                print(json.dumps(outcome.to_dict()) if args.json else describe(outcome), flush=True)
    finally:
        logging.disable(logging.NOTSET)  # main() may run inside another program (the tests do)
    failed = [outcome.name for outcome in outcomes if not outcome.ok]
    if not args.json:
        print(f"{len(failed)} of {len(outcomes)} targets failed: {', '.join(failed)}" if failed else f"all {len(outcomes)} targets passed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
