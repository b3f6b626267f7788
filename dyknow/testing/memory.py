"""The peak memory of a command, as the kernel counted it for that command alone.

``ru_maxrss`` from ``wait4`` on a child looks right and is not: on Linux a child's high-water mark
starts at its parent's resident size when it was forked, so a command started by a 300 MiB pytest
reads as 300 MiB even if it never held more than 20. :func:`peak_run` starts the command from a
small launcher (a bare interpreter, about 10 MiB) that forks, executes the command and reads
``wait4`` itself, so the figure is the command's own (or the launcher's 10 MiB, if larger)::

    from dyknow.testing.memory import peak_run
    code, peak_mib = peak_run(["dyknow", "replay", "bomb.mcap"], timeout_s=60)
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

__all__ = ["peak_run"]

# argv: [outfile, command...]: run the command as our child, write its exit code and ru_maxrss (KiB)
_LAUNCHER = """\
import os, sys
pid = os.fork()
if pid == 0:
    try:
        os.execvp(sys.argv[2], sys.argv[2:])
    finally:
        os._exit(127)
_, status, usage = os.wait4(pid, 0)
with open(sys.argv[1], "w") as out:
    out.write(f"{os.waitstatus_to_exitcode(status)} {usage.ru_maxrss}")
"""


def peak_run(
    argv: Sequence[str],
    *,
    timeout_s: float,
    env: Mapping[str, str] | None = None,
    cwd: str | os.PathLike[str] | None = None,
    stdout: IO[Any] | int | None = subprocess.DEVNULL,
    stderr: IO[Any] | int | None = None,
) -> tuple[int, float]:
    """Run ``argv`` to its end: its exit code and its peak resident memory in MiB.

    After ``timeout_s`` the command (and everything it started) is killed, and its exit code is
    that of the kill (``-9``). ``stdout``/``stderr`` are as for :class:`subprocess.Popen`.
    """
    if not argv:
        raise ValueError("peak_run needs a command: argv is empty")
    with tempfile.TemporaryDirectory(prefix="dyknow-peak-") as folder:
        result = Path(folder) / "result"
        proc = subprocess.Popen(
            [sys.executable, "-I", "-S", "-c", _LAUNCHER, str(result), *argv],
            stdout=stdout,
            stderr=stderr,
            env=None if env is None else dict(env),
            cwd=cwd,
            start_new_session=True,  # a timeout kills the launcher and the command together
        )
        killer = threading.Timer(timeout_s, os.killpg, (proc.pid, signal.SIGKILL))
        killer.start()
        try:
            proc.wait()
        finally:
            killer.cancel()
        if not result.exists():  # killed before the command ended
            return proc.returncode, 0.0
        code, kib = result.read_text().split()
        return int(code), int(kib) / 1024
