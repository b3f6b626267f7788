"""Several hosts on one Linux machine, for tests of a distributed system: network namespaces.

:class:`Hosts` makes one network namespace per host and joins them with veth links to a bridge
in a namespace of its own, like machines on one switch. Each host has its own loopback and an
address ``10.77.0.<n>`` on ``eth0``. Faults on a host's link:

- :meth:`Hosts.cut` takes it down (the host is cut off, its processes keep running), or with
  ``silent=True`` drops every packet on it (``nftables``) while it stays up, and
  :meth:`Hosts.restore` brings it back;
- :meth:`Hosts.loss` drops a share of the packets both ways at random (``nftables``: Debian's
  ``nft``), on ``eth0`` only, so the host's own loopback is untouched;
- :meth:`Hosts.bandwidth` limits the link both ways with a token bucket (``tc tbf``);
- ``tc netem`` delay and loss where the kernel has it (this one may not: :attr:`Hosts.shaping`).

Each process started with :meth:`Hosts.popen` gets a ``/dev/shm`` of its own (a private tmpfs):
a network namespace does not isolate shared memory, and Zenoh hands large payloads to any peer
that can open its shared-memory pool, so without it frames would not cross the simulated link
at all. Nothing touches the machine's own network: every address lives inside the namespaces,
which are deleted on close.

It needs root (``CAP_NET_ADMIN``) and the ``ip`` tool; :func:`unavailable` says why it cannot
run here, or None (:func:`faults_unavailable`: the same for loss and bandwidth)::

    from dyknow.testing.hosts import Hosts

    with Hosts(["robot", "station"]) as hosts:
        proc = hosts.popen("robot", ["dyknow", "manager", "--listen", f"tcp/{hosts.address('robot')}:7447"])
        hosts.loss("robot", 5)  # 5 % of the robot's packets lost, both ways
        hosts.cut("robot")  # the robot's link goes down: the station loses it when the lease expires
"""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["Hosts", "faults_unavailable", "unavailable"]

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


def faults_unavailable() -> str | None:
    """Why :meth:`Hosts.loss`, :meth:`Hosts.bandwidth` or a silent :meth:`Hosts.cut` cannot work here (no ``nft`` or ``tc``), or None."""
    missing = [tool for tool, package in (("nft", "nftables"), ("tc", "iproute2")) if shutil.which(tool) is None]
    if missing:
        return f"{' and '.join(missing)} not installed (apt-get install nftables iproute2)"
    return None


class Hosts:
    """Hosts as network namespaces on one bridge; a context manager that deletes them all.

    ``delay_ms`` and ``loss_percent`` shape every host's link with ``tc netem`` when the kernel
    has it; :attr:`shaping` says what was applied, or why nothing was.
    """

    def __init__(
        self,
        names: Sequence[str],
        *,
        delay_ms: float | None = None,
        loss_percent: float | None = None,
        addresses: Mapping[str, str] | None = None,
    ) -> None:
        if len(names) > 200 or len(set(names)) != len(names):
            raise ValueError(f"hosts {list(names)!r}: expected up to 200 distinct names")
        self.names = list(names)
        # ``addresses``: a host's own address instead of 10.77.0.<n> (to run a documented example
        # as written); all on one /24, as hosts on one switch
        self._addresses = {name: (addresses or {}).get(name, f"10.77.0.{i + 1}") for i, name in enumerate(self.names)}
        nets = {a.rsplit(".", 1)[0] for a in self._addresses.values()}
        if len(nets) != 1 or len(set(self._addresses.values())) != len(self.names):
            raise ValueError(f"addresses {self._addresses!r}: expected distinct IPv4 addresses on one /24")
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
        return self._addresses[name]

    def command(self, name: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside host ``name``'s namespace."""
        return ["ip", "netns", "exec", self.namespace(name), *argv]

    def popen(self, name: str, argv: Sequence[str], *, private_shm: bool = True, **kwargs: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` on host ``name`` (keyword arguments go to :class:`subprocess.Popen`).

        ``private_shm``: with a ``/dev/shm`` of its own (see the module documentation)."""
        if private_shm:
            shell = 'mount -t tmpfs -o size=512m,mode=1777 tmpfs /dev/shm && exec "$0" "$@"'
            argv = ["unshare", "--mount", "--propagation", "private", "sh", "-c", shell, *argv]
        return subprocess.Popen(self.command(name, argv), **kwargs)

    def loss(self, name: str, percent: float) -> None:
        """Drop ``percent`` % of the packets of host ``name``'s link, at random, both ways (0: none)."""
        if not 0 <= percent <= 100:
            raise ValueError(f"loss: got {percent} %; expected 0 to 100")
        ns = self.namespace(name)
        subprocess.run(["ip", "netns", "exec", ns, "nft", "delete", "table", "inet", "dyknow_faults"], capture_output=True)
        if percent == 0:
            return
        share = round(percent * 100)  # in 1/10,000
        rules = f"""
            table inet dyknow_faults {{
                chain incoming {{ type filter hook input priority 0; iifname "eth0" numgen random mod 10000 < {share} drop; }}
                chain outgoing {{ type filter hook output priority 0; oifname "eth0" numgen random mod 10000 < {share} drop; }}
            }}
        """
        done = subprocess.run(["ip", "netns", "exec", ns, "nft", "-f", "-"], input=rules, capture_output=True, text=True)
        if done.returncode != 0:
            raise OSError(f"nft on host {name!r}: {done.stderr.strip() or 'failed'}")

    def bandwidth(self, name: str, rate: str | None) -> None:
        """Limit host ``name``'s link to ``rate`` both ways (``tc`` units: ``1mbit``, ``500kbit``; None: no limit)."""
        sides = [(self.namespace(name), "eth0"), (self.lan, self._port(name))]  # out of the host, and into it
        for ns, dev in sides:
            subprocess.run(["tc", "-n", ns, "qdisc", "del", "dev", dev, "root"], capture_output=True)
            if rate is None:
                continue
            tbf = ["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "tbf", "rate", rate, "burst", "32kbit", "latency", "400ms"]
            done = subprocess.run(tbf, capture_output=True, text=True)
            if done.returncode != 0:
                raise OSError(f"tc tbf on host {name!r}: {done.stderr.strip() or 'failed'}")

    def cut(self, name: str, *, silent: bool = False) -> None:
        """Cut host ``name`` off from the others (its processes keep running): its link taken down,
        or with ``silent`` left up while every packet on it is dropped both ways (``nftables``),
        as a firewall or a radio out of range does: nothing tells either side the link is gone."""
        if not silent:
            self._ip("-n", self.lan, "link", "set", self._port(name), "down")
            return
        rules = """
            table inet dyknow_cut {
                chain incoming { type filter hook input priority -10; iifname "eth0" drop; }
                chain outgoing { type filter hook output priority -10; oifname "eth0" drop; }
            }
        """
        done = subprocess.run(["ip", "netns", "exec", self.namespace(name), "nft", "-f", "-"], input=rules, capture_output=True, text=True)
        if done.returncode != 0:
            raise OSError(f"nft on host {name!r}: {done.stderr.strip() or 'failed'}")

    def restore(self, name: str) -> None:
        """Bring host ``name``'s link back up, and lift a silent cut."""
        subprocess.run(["ip", "netns", "exec", self.namespace(name), "nft", "delete", "table", "inet", "dyknow_cut"], capture_output=True)
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
