"""What ``dyknow replay`` costs in memory on MCAP decompression bombs (issue 38, item 6).

Writes the bombs of :func:`dyknow.testing.bombs.write_bombs` (a 33 KB zstd chunk holding 1 GiB, a
130 KB one holding 4 GiB, a chunk whose zstd frame states 1 GiB where the chunk declares 1 KiB,
a 4.2 MiB lz4 chunk holding 1 GiB that declares 1 KiB, 16 overlapping chunks of 200 MiB, 256 MiB
of empty messages), runs ``dyknow replay FILE --rate max`` on each in a child process, and
reports its exit code, its first line of errors and its peak resident memory (``ru_maxrss`` of
that command alone, by :func:`dyknow.testing.memory.peak_run`).

Target: every bomb refused (exit 1, a one-line error naming the file and the chunk's offset)
with a peak of at most 1.2 GiB: the default bound of 1 GiB held (``--max-memory-bytes``), plus the
interpreter. ``--source DIR`` runs the dyknow found in DIR instead (a checkout of another
commit), to measure it the same way.

    python benchmarks/mcap_bombs.py
    python benchmarks/mcap_bombs.py --source /tmp/before --bombs zstd-1g,lz4-1g-declares-1k
    python benchmarks/mcap_bombs.py -- --max-memory-bytes 268435456   # options for every replay
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from dyknow.testing.bombs import write_bombs
from dyknow.testing.memory import peak_run

from harness import free_ports, machine, write_json

TARGET_PEAK_MIB = 1.2 * 1024


def replay_peak(path: Path, extra: list[str], source: str | None, timeout_s: float) -> dict[str, Any]:
    """Replay ``path`` in a child process: its exit code, first error line, seconds and peak RSS."""
    env = dict(os.environ)
    if source is not None:
        env["PYTHONPATH"] = source
    port = free_ports(1)[0]
    argv = [sys.executable, "-m", "dyknow.cli", "replay", str(path), "--rate", "max", "--wait", "0",
            "--connect", f"tcp/127.0.0.1:{port}", *extra]  # fmt: skip
    with tempfile.TemporaryFile() as err:
        start = time.monotonic()
        code, peak_mib = peak_run(argv, timeout_s=timeout_s, env=env, stderr=err)
        err.seek(0)
        lines = [line for line in err.read().decode(errors="replace").splitlines() if line.strip()]
    return {
        "exit": code,
        "seconds": round(time.monotonic() - start, 2),
        "peak_mib": round(peak_mib, 1),
        "error": lines[-1] if lines else "",
    }


def main() -> None:
    """Write the bombs, replay each, print the table (and write the JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", metavar="DIR", help="run the dyknow in DIR (put first on PYTHONPATH) instead of the installed one")
    parser.add_argument("--bombs", metavar="A,B", help="only these bombs (default all)")
    parser.add_argument("--timeout", type=float, default=120.0, metavar="S", help="kill a replay after S seconds (default 120)")
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the results as JSON")
    parser.add_argument("extra", nargs="*", help="options given to every replay (after --)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="dyknow-bombs-") as folder:
        bombs = write_bombs(folder)
        wanted = args.bombs.split(",") if args.bombs else list(bombs)
        rows = []
        print(f"| bomb | file | exit | peak RSS | error | target (refused, <= {TARGET_PEAK_MIB:.0f} MiB) |")
        print("|---|---|---|---|---|---|")
        for name in wanted:
            path = bombs[name]
            result = replay_peak(path, args.extra, args.source, args.timeout)
            met = result["exit"] == 1 and result["peak_mib"] <= TARGET_PEAK_MIB
            rows.append({"bomb": name, "file_bytes": path.stat().st_size, **result, "met": met})
            error = result["error"].replace(str(path), "FILE").replace("|", "/")
            print(
                f"| {name} | {path.stat().st_size} B | {result['exit']} | {result['peak_mib']} MiB | {error} | {'yes' if met else 'no'} |",
                flush=True,
            )
    if args.json:
        write_json(args.json, {"machine": machine(), "source": args.source, "extra": args.extra, "results": rows})


if __name__ == "__main__":
    main()
