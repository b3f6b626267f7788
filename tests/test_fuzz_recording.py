"""Fuzzing the MCAP reader: a damaged recording reads, or raises RecordingError, and never hangs.

The seeds are recordings from our own writer (small, synthetic, one per chunk compression), the
Foxglove file in ``tests/mcap`` and the real files of the data folder (``$DYKNOW_DATA``: other
writers' recordings and a few conformance variants). Each example truncates, flips bits,
replaces record lengths with odd values, overwrites, inserts or deletes bytes, then reads the
whole file as a user would (summary, messages, records, replay with decoding; strictly and with
``recover``) on a thread with a time bound. Derandomized and bounded for CI; ``tools/fuzz.py
--targets mcap`` runs the same property randomized for longer.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import example

from dyknow.recording import Recording
from dyknow.testing.fuzzing import MutatedRecording, check_recording, derandomized, mcap_property, write_seed_recordings
from tests.conftest import REPO

TIMEOUT_S = 60.0  # generous: the largest seed reads in well under a second
ODD = 2**64 - 1


@pytest.fixture(scope="module")
def ours(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Our writer's seed recordings and the Foxglove file kept in the repository."""
    paths = write_seed_recordings(tmp_path_factory.mktemp("seeds"))
    paths.append(REPO / "tests" / "mcap" / "foxglove-protobuf.mcap")
    return {path.name: path for path in paths}


@pytest.fixture(scope="module")
def real(data_dir: Path) -> dict[str, Path]:
    """Other writers' recordings from the data folder, and per conformance base the plain variant
    and the one with every feature (chunks, indexes, padding, summary, ...)."""
    paths = sorted((data_dir / "mcap" / "real").glob("*.mcap"))
    for base in sorted((data_dir / "mcap" / "conformance").iterdir()):
        variants = sorted(base.glob("*.mcap"))
        if variants:
            paths += [variants[0], max(variants, key=lambda p: len(p.name))]
    assert len(paths) >= 4 + 2 * 6, f"the data folder lacks recordings: {paths}"
    return {path.name: path for path in paths}


def test_every_seed_reads_whole(ours: dict[str, Path], real: dict[str, Path]) -> None:
    for name, path in {**ours, **real}.items():
        with Recording(path) as recording:  # strictly: an undamaged seed has no problem
            assert recording.problem is None, name
        check_recording(path, TIMEOUT_S)


def _fuzz(seeds: dict[str, Path], folder: Path, max_examples: int, *examples: MutatedRecording) -> None:
    prop = mcap_property(seeds, folder, TIMEOUT_S)
    run = prop.hypothesis_test(derandomized(max_examples))
    for extra in examples:
        run = example(extra)(run)
    run()


def test_a_damaged_recording_of_ours_reads_or_is_a_recording_error(ours: dict[str, Path], tmp_path: Path) -> None:
    _fuzz(
        ours,
        tmp_path,
        1500,
        MutatedRecording("ours-zstd.mcap", (("length", 0, ODD),)),  # the Header claims 2**64-1 bytes
        MutatedRecording("ours-none.mcap", (("length", 5, 2**63),)),  # a record inside an uncompressed chunk
        MutatedRecording("ours-lz4.mcap", (("truncate", -20, 0),)),  # cut inside the footer
        MutatedRecording("ours-none.mcap", (("u32", 9 + 8 + 2, 2**32 - 1),)),  # a string length in the Header
    )


def test_a_damaged_real_recording_reads_or_is_a_recording_error(real: dict[str, Path], tmp_path: Path) -> None:
    _fuzz(
        real,
        tmp_path,
        3000,
        MutatedRecording("custom-camera-model.mcap", (("flip", 400_000, 3),)),  # inside a JPEG: decoding fails, bytes delivered
        MutatedRecording("talker.mcap", (("length", 3, 9),)),
        MutatedRecording("cdr_test_0.mcap", (("truncate", 5000, 0), ("length", 1, 0))),
    )
