"""Several hosts on one Linux machine, for tests of a distributed system: network namespaces.

:class:`Hosts` makes one network namespace per host and joins them with veth links to a bridge
in a namespace of its own, like machines on one switch. Each host has its own loopback and an
address ``10.77.0.<n>`` on ``eth0``; a link can be taken down (:meth:`Hosts.cut`) to cut a host
off, and shaped with ``tc netem`` delay and loss where the kernel has it. Nothing touches the
machine's own network: every address lives inside the namespaces, which are deleted on close.

It needs root (``CAP_NET_ADMIN``) and the ``ip`` tool; :func:`unavailable` says why it cannot
run here, or None::

    from dyknow.testing.hosts import Hosts

    with Hosts(["robot", "station"]) as hosts:
        proc = hosts.popen("robot", ["dyknow", "manager", "--listen", f"tcp/{hosts.address('robot')}:7447"])
        hosts.cut("robot")  # the robot's link goes down: the station loses it when the lease expires
"""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess
from collections.abc import Sequence
from typing import Any

__all__ = ["Hosts", "unavailable"]

_serial = itertools.count(1)


def unavailable() -> str | None:
    """Why namespaces cannot be made on this machine (not root, no ``ip``), or None when they can."""
    if shutil.which("ip") is None:
        return "the 'ip' tool (iproute2) is not installed"
    if os.geteuid() != 0:
        return "network namespaces need root (CAP_NET_ADMIN)"
    probe = f"dk-probe-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"cannot create a network namespace: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


class Hosts:
    """Hosts as network namespaces on one bridge; a context manager that deletes them all.

    ``delay_ms`` and ``loss_percent`` shape every host's link with ``tc netem`` when the kernel
    has it; :attr:`shaping` says what was applied, or why nothing was.
    """

    def __init__(self, names: Sequence[str], *, delay_ms: float | None = None, loss_percent: float | None = None) -> None:
        if len(names) > 200 or len(set(names)) != len(names):
            raise ValueError(f"hosts {list(names)!r}: expected up to 200 distinct names")
        self.names = list(names)
        self.tag = f"dk{os.getpid() % 100000}x{next(_serial)}"
        self.lan = f"{self.tag}-lan"
        self._namespaces: list[str] = []
        self.shaping = "none asked"
        try:
            self._make(delay_ms, loss_percent)
        except BaseException:
            self.close()
            raise

    def namespace(self, name: str) -> str:
        """The network namespace of host ``name``."""
        return f"{self.tag}-{self.names.index(name)}"

    def address(self, name: str) -> str:
        """Host ``name``'s address on the shared network."""
        return f"10.77.0.{self.names.index(name) + 1}"

    def command(self, name: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside host ``name``'s namespace."""
        return ["ip", "netns", "exec", self.namespace(name), *argv]

    def popen(self, name: str, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` on host ``name`` (keyword arguments go to :class:`subprocess.Popen`)."""
        return subprocess.Popen(self.command(name, argv), **kwargs)

    def cut(self, name: str) -> None:
        """Take host ``name``'s link down: it is cut off from the others (its processes keep running)."""
        self._ip("-n", self.lan, "link", "set", self._port(name), "down")

    def restore(self, name: str) -> None:
        """Bring host ``name``'s link back up."""
        self._ip("-n", self.lan, "link", "set", self._port(name), "up")

    def close(self) -> None:
        """Delete every namespace (and so every link) this made; safe twice."""
        for ns in reversed(self._namespaces):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self._namespaces.clear()

    def __enter__(self) -> Hosts:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- building

    def _port(self, name: str) -> str:
        return f"p{self.names.index(name)}"

    def _ip(self, *args: str) -> None:
        result = subprocess.run(["ip", *args], capture_output=True, text=True)
        if result.returncode != 0:
            raise OSError(f"ip {' '.join(args)}: {result.stderr.strip()}")

    def _make(self, delay_ms: float | None, loss_percent: float | None) -> None:
        self._ip("netns", "add", self.lan)
        self._namespaces.append(self.lan)
        self._ip("-n", self.lan, "link", "add", "br0", "type", "bridge")
        self._ip("-n", self.lan, "link", "set", "br0", "up")
        netem = [*(["delay", f"{delay_ms}ms"] if delay_ms else []), *(["loss", f"{loss_percent}%"] if loss_percent else [])]
        refused: list[str] = []
        for name in self.names:
            ns = self.namespace(name)
            self._ip("netns", "add", ns)
            self._namespaces.append(ns)
            self._ip("-n", ns, "link", "set", "lo", "up")
            self._ip("-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", self._port(name), "netns", self.lan)
            self._ip("-n", ns, "addr", "add", f"{self.address(name)}/24", "dev", "eth0")
            self._ip("-n", ns, "link", "set", "eth0", "up")
            self._ip("-n", self.lan, "link", "set", self._port(name), "master", "br0")
            self._ip("-n", self.lan, "link", "set", self._port(name), "up")
            if netem:
                shaped = subprocess.run(["tc", "-n", ns, "qdisc", "add", "dev", "eth0", "root", "netem", *netem], capture_output=True, text=True)
                if shaped.returncode != 0:
                    refused.append(shaped.stderr.strip() or "tc failed")
        if netem:
            self.shaping = f"netem {' '.join(netem)}" if not refused else f"unavailable ({refused[0]}): links are not shaped"
