"""Install dyknow into an environment and show what takes the time: what ``make`` runs.

    python tools/install.py [TARGET] [--log FILE]

``TARGET`` is what pip installs (default ``-e .``; ``-e '.[test]'``, ``-e '.[docs]'``). pip runs
quietly, but this shows its steps as they come (dependencies collected, dyknow being built) and
the progress lines of ``setup.py`` (the lines that start with ``dyknow:``: mypyc compiling the
hot-path modules, the longest step of a first install), with the time spent; every line pip
printed goes to ``--log`` (default ``.venv/install.log``), and its last lines are shown on
failure. ``DYKNOW_PURE_PYTHON=1`` skips the compilation (the hot paths then run about half as
fast); the first line says so.

Exit status: pip's.
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

#: pip's lines worth showing while it works (the rest goes to the log).
SHOWN = ("Collecting ", "Building editable", "Building wheel", "Installing collected", "Successfully installed", "ERROR", "error:")


def main(argv: list[str] | None = None) -> int:
    """Run pip, showing its steps and setup.py's progress; return pip's exit status."""
    parser = argparse.ArgumentParser(description="install dyknow, showing the progress of the compilation")
    parser.add_argument("target", nargs="?", default="-e .", help="what pip installs (default: -e .)")
    parser.add_argument("--log", default=".venv/install.log", help="where every line of pip's goes (default .venv/install.log)")
    args = parser.parse_args(argv)
    if os.environ.get("DYKNOW_PURE_PYTHON"):
        print("dyknow: DYKNOW_PURE_PYTHON is set: the hot-path modules stay interpreted (no compilation; they run about half as fast)")
    else:
        print("dyknow: installing; the first install compiles the hot-path modules with mypyc: about 2 minutes on a quiet "
              "machine, up to 6 on a loaded one (DYKNOW_PURE_PYTHON=1 skips it; they then run about half as fast)", flush=True)  # fmt: skip
    started = time.monotonic()
    log = Path(args.log)
    log.parent.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "pip", "install", "-v", *shlex.split(args.target)]
    last = [time.monotonic()]
    done = threading.Event()

    def heartbeat() -> None:  # a long silent step (a C compiler at work) is not a hang
        while not done.wait(5):
            if time.monotonic() - last[0] >= 30:
                print(f"dyknow: still working ({time.monotonic() - started:.0f} s so far)", flush=True)
                last[0] = time.monotonic()

    threading.Thread(target=heartbeat, daemon=True).start()
    tail: list[str] = []
    with log.open("w") as out, subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as pip:
        assert pip.stdout is not None
        for line in pip.stdout:
            out.write(line)
            tail = [*tail[-39:], line]
            text = line.strip()
            if text.startswith("dyknow: ") or text.startswith(SHOWN):
                print(f"[{time.monotonic() - started:4.0f} s] {text}", flush=True)
                last[0] = time.monotonic()
        status = pip.wait()
    done.set()
    if status != 0:
        print("".join(tail), end="", file=sys.stderr)
        print(f"dyknow: pip failed (exit {status}); every line is in {log}", file=sys.stderr)
    else:
        print(f"dyknow: installed in {time.monotonic() - started:.0f} s (pip's output: {log})", flush=True)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
