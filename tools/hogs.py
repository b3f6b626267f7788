"""Run a command beside CPU hogs: how a test (or the whole suite) is shown to pass on a busy machine.

    python tools/hogs.py [--per-core N] [--repeat K] -- COMMAND [ARG ...]

Starts ``N`` busy processes per core (default 2: two hogs per core, as CI's load can be), each a
Python loop that never sleeps, at the same priority as the command; runs ``COMMAND`` ``K`` times
(default 1) beside them, stopping at the first run that fails; then stops the hogs. Each run
prints one line: its exit status, its wall time and the load average at its end. Examples::

    python tools/hogs.py -- make test                           # the suite beside 4 hogs (2 cores)
    python tools/hogs.py --repeat 10 -- .venv/bin/python -m pytest tests/test_x.py -k new_test

Exit status: the last run's (0 when every run passed).
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import subprocess
import sys
import time

_PR_SET_PDEATHSIG = 1  # (linux/prctl.h)

#: A hog: a busy loop that never sleeps, never allocates and never ends by itself.
HOG = "while True: pass"


def start_hogs(count: int) -> list[subprocess.Popen[bytes]]:
    """Start ``count`` hogs (each ends with :func:`stop_hogs`); each names this process in its
    arguments (``hog-of=PID``), so that they can be told apart from another run's."""
    return [
        subprocess.Popen([sys.executable, "-c", HOG, f"hog-of={os.getpid()}"], stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent)
        for _ in range(count)
    ]


def _die_with_parent() -> None:
    """(In the hog, before it starts.) Be killed when this process ends, however it ends: a hogs
    run stopped by a signal left its hogs busy for the runs after it (Linux's PR_SET_PDEATHSIG)."""
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)


def stop_hogs(hogs: list[subprocess.Popen[bytes]]) -> None:
    """Kill the hogs and wait for them."""
    for hog in hogs:
        hog.kill()
    for hog in hogs:
        hog.wait()


def main(argv: list[str] | None = None) -> int:
    """Run the command beside the hogs; return its exit status."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog="COMMAND follows --")
    parser.add_argument("--per-core", type=int, default=2, metavar="N", help="hogs per core (default 2)")
    parser.add_argument("--repeat", type=int, default=1, metavar="K", help="runs of the command, stopping at the first failure (default 1)")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="the command, after --")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command given: put it after --, for example: python tools/hogs.py -- make test")
    if args.per_core < 0 or args.repeat < 1:
        parser.error(f"--per-core {args.per_core} --repeat {args.repeat}: expected --per-core 0 or more and --repeat 1 or more")
    cores = os.cpu_count() or 1
    hogs = start_hogs(args.per_core * cores)
    print(f"hogs: {len(hogs)} busy processes beside the command ({args.per_core} per core, {cores} cores)", flush=True)
    status = 0
    try:
        for run in range(1, args.repeat + 1):
            started = time.monotonic()
            status = subprocess.run(command).returncode
            load = os.getloadavg()[0]
            print(f"hogs: run {run} of {args.repeat}: exit status {status} in {time.monotonic() - started:.0f} s, load average {load:.1f}", flush=True)
            if status != 0:
                break
    finally:
        stop_hogs(hogs)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
