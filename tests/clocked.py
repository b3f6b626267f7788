"""Run a ``dyknow`` command, saying first how this process's wall clock stands against the
monotonic clock: for tests that fake the wall clock of a process (libfaketime).

Run as ``python -m tests.clocked ARGS...`` (the arguments of ``dyknow``). Its first line is JSON,
``{"event": "clock", "realtime_ns": ..., "monotonic_ns": ..., "read_ns": ...}``: the wall clock,
read between two readings of the monotonic clock ``read_ns`` apart (their middle is given);
the command then runs in the same process. Under libfaketime with the monotonic clock left alone
(``FAKETIME_DONT_FAKE_MONOTONIC=1``), only the wall clock is faked, and the monotonic clock is the
machine's (network namespaces share it): so the wall clock's offset from the machine's is this
line's ``realtime_ns - monotonic_ns`` less the same difference read in any unfaked process, at the
moment of this line; with a speed (``x1.0001``), it then grows at that rate less one.
"""

from __future__ import annotations

import json
import sys
import time

from dyknow.cli import run

if __name__ == "__main__":
    before, realtime, after = time.monotonic_ns(), time.time_ns(), time.monotonic_ns()  # (a faked clock is slow to read)
    print(json.dumps({"event": "clock", "realtime_ns": realtime, "monotonic_ns": (before + after) // 2, "read_ns": after - before}), flush=True)
    run(sys.argv[1:])
