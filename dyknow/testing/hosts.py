"""Several hosts on one Linux machine, for tests of a distributed system: network namespaces.

:class:`Hosts` makes one network namespace per host and joins them with veth links to a bridge
in a namespace of its own, like machines on one switch. Each host has its own loopback and an
address ``10.77.0.<n>`` on ``eth0``. With ``networks``, several networks instead of one (two
sites and the WAN between their gateways, say): a bridge each, a host on several (a gateway) with
an interface on each (``eth0``, ``eth1``, ...) and address ``10.77.<k>.<n>`` on the k-th; no host
forwards packets, so hosts of different networks reach each other only through a process that
relays, such as a Zenoh router on a gateway. Faults on a host's link (all of its links):

- :meth:`Hosts.cut` takes it down (the host is cut off, its processes keep running), or with
  ``silent=True`` drops every packet on it (``nftables``) while it stays up, and
  :meth:`Hosts.restore` brings it back;
- :meth:`Hosts.loss` drops a share of the packets both ways at random (``nftables``: Debian's
  ``nft``), on its ``eth`` interfaces only, so the host's own loopback is untouched;
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

    # two sites joined by their gateways only: site-a's hosts cannot reach site-b's
    sites = {"site-a": ["station", "gw-a"], "site-b": ["robot", "gw-b"], "wan": ["gw-a", "gw-b"]}
    with Hosts(["station", "gw-a", "robot", "gw-b"], networks=sites) as hosts:
        hosts.address("gw-a", "wan")  # 10.77.2.2
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
    """Hosts as network namespaces on one bridge (or on several, ``networks``: network name -> its
    hosts); a context manager that deletes them all.

    ``addresses``: a host's own address, by name (on its first network) or ``host@network``.
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
        networks: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        if len(names) > 200 or len(set(names)) != len(names):
            raise ValueError(f"hosts {list(names)!r}: expected up to 200 distinct names")
        self.names = list(names)
        # ``networks``: several networks (sites, a WAN between their gateways) instead of one
        # switch: network name -> the hosts on it. A host on several (a gateway) has an
        # interface on each, eth0, eth1, ... in this order, and forwards nothing between them.
        nets = {name: list(on) for name, on in networks.items()} if networks is not None else {"lan": list(self.names)}
        if networks is not None:
            if len(nets) > 200 or not all(on and len(set(on)) == len(on) and set(on) <= set(self.names) for on in nets.values()):
                raise ValueError(f"networks {networks!r}: expected up to 200, each with distinct hosts of {self.names!r}")
            if set(self.names) - {h for on in nets.values() for h in on}:
                raise ValueError(f"networks {networks!r}: hosts {sorted(set(self.names) - {h for on in nets.values() for h in on})!r} are on none")
        self.networks = list(nets)
        # ``addresses``: a host's own address instead of 10.77.<k>.<n> (to run a documented example
        # as written), by host (its first network) or by ``host@network``; each network on one /24
        given = dict(addresses or {})
        unknown = [k for k in given if k.partition("@")[0] not in self.names or (k.partition("@")[2] or self.networks[0]) not in nets]
        if unknown:
            raise ValueError(f"addresses: {unknown!r} name no host (or host@network) of {self.names!r} on {self.networks!r}")
        # per host: (network, interface, bridge port, address) for each network it is on
        self._links: dict[str, list[tuple[str, str, str, str]]] = {name: [] for name in self.names}
        for k, (network, on) in enumerate(nets.items()):
            for name in on:
                place = self.names.index(name)
                first = not self._links[name]
                address = given.get(f"{name}@{network}") or (given.get(name) if first else None) or f"10.77.{k}.{place + 1}"
                self._links[name].append((network, f"eth{len(self._links[name])}", f"p{place}", address))
            found = [a for name in on for net, _, _, a in self._links[name] if net == network]
            if len({a.rsplit(".", 1)[0] for a in found}) != 1 or len(set(found)) != len(found):
                raise ValueError(f"addresses {dict(zip(on, found, strict=True))!r} of network {network!r}: expected distinct IPv4 addresses on one /24")
        self.tag = f"dk{os.getpid() % 100000}x{next(_serial)}"
        self.lan = f"{self.tag}-lan"  # the (first) network's bridge
        self._bridges = {network: self.lan if k == 0 else f"{self.tag}-lan{k}" for k, network in enumerate(self.networks)}
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

    def address(self, name: str, network: str | None = None) -> str:
        """Host ``name``'s address on ``network`` (default: the first network it is on)."""
        for on, _, _, address in self._links[name]:
            if network is None or on == network:
                return address
        raise ValueError(f"host {name!r} is not on network {network!r} (it is on {[n for n, *_ in self._links[name]]!r})")

    def _on(self, name: str, network: str | None) -> list[tuple[str, str, str, str]]:
        """Host ``name``'s links: every one, or the one on ``network``."""
        links = [link for link in self._links[name] if network is None or link[0] == network]
        if not links:
            raise ValueError(f"host {name!r} is not on network {network!r} (it is on {[n for n, *_ in self._links[name]]!r})")
        return links

    def _devices(self, name: str, network: str | None = None) -> str:
        """nft's match of host ``name``'s network interfaces (``"eth0"``, or a set of them)."""
        devices = [f'"{dev}"' for _, dev, _, _ in self._on(name, network)]
        return devices[0] if len(devices) == 1 else "{ " + ", ".join(devices) + " }"

    def command(self, name: str, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside host ``name``'s namespace."""
        return ["ip", "netns", "exec", self.namespace(name), *argv]

    def argv(self, name: str, argv: Sequence[str], *, private_shm: bool = True) -> list[str]:
        """The command line that runs ``argv`` on host ``name`` (what :meth:`popen` starts).

        ``private_shm``: with a ``/dev/shm`` of its own (see the module documentation)."""
        if private_shm:
            shell = 'mount -t tmpfs -o size=512m,mode=1777 tmpfs /dev/shm && exec "$0" "$@"'
            argv = ["unshare", "--mount", "--propagation", "private", "sh", "-c", shell, *argv]
        return self.command(name, argv)

    def popen(self, name: str, argv: Sequence[str], *, private_shm: bool = True, **kwargs: Any) -> subprocess.Popen[Any]:
        """Start ``argv`` on host ``name`` (keyword arguments go to :class:`subprocess.Popen`).

        ``private_shm``: with a ``/dev/shm`` of its own (see the module documentation)."""
        return subprocess.Popen(self.argv(name, argv, private_shm=private_shm), **kwargs)

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
                chain incoming {{ type filter hook input priority 0; iifname {self._devices(name)} numgen random mod 10000 < {share} drop; }}
                chain outgoing {{ type filter hook output priority 0; oifname {self._devices(name)} numgen random mod 10000 < {share} drop; }}
            }}
        """
        done = subprocess.run(["ip", "netns", "exec", ns, "nft", "-f", "-"], input=rules, capture_output=True, text=True)
        if done.returncode != 0:
            raise OSError(f"nft on host {name!r}: {done.stderr.strip() or 'failed'}")

    def bandwidth(self, name: str, rate: str | None) -> None:
        """Limit host ``name``'s link to ``rate`` both ways (``tc`` units: ``1mbit``, ``500kbit``; None: no limit)."""
        # out of the host, and into it, on each of its networks
        sides = [side for network, dev, port, _ in self._links[name] for side in ((self.namespace(name), dev), (self._bridges[network], port))]
        for ns, dev in sides:
            subprocess.run(["tc", "-n", ns, "qdisc", "del", "dev", dev, "root"], capture_output=True)
            if rate is None:
                continue
            tbf = ["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "tbf", "rate", rate, "burst", "32kbit", "latency", "400ms"]
            done = subprocess.run(tbf, capture_output=True, text=True)
            if done.returncode != 0:
                raise OSError(f"tc tbf on host {name!r}: {done.stderr.strip() or 'failed'}")

    def cut(self, name: str, *, silent: bool = False, network: str | None = None) -> None:
        """Cut host ``name`` off from the others (its processes keep running): its link taken down,
        or with ``silent`` left up while every packet on it is dropped both ways (``nftables``),
        as a firewall or a radio out of range does: nothing tells either side the link is gone.
        ``network``: only its link to that network (a gateway's WAN, say); default every link."""
        if not silent:
            for net, _, port, _ in self._on(name, network):
                self._ip("-n", self._bridges[net], "link", "set", port, "down")
            return
        rules = f"""
            table inet dyknow_cut {{
                chain incoming {{ type filter hook input priority -10; iifname {self._devices(name, network)} drop; }}
                chain outgoing {{ type filter hook output priority -10; oifname {self._devices(name, network)} drop; }}
            }}
        """
        done = subprocess.run(["ip", "netns", "exec", self.namespace(name), "nft", "-f", "-"], input=rules, capture_output=True, text=True)
        if done.returncode != 0:
            raise OSError(f"nft on host {name!r}: {done.stderr.strip() or 'failed'}")

    def restore(self, name: str) -> None:
        """Bring host ``name``'s links back up, and lift a silent cut."""
        subprocess.run(["ip", "netns", "exec", self.namespace(name), "nft", "delete", "table", "inet", "dyknow_cut"], capture_output=True)
        for network, _, port, _ in self._links[name]:
            self._ip("-n", self._bridges[network], "link", "set", port, "up")

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

    def _ip(self, *args: str) -> None:
        result = subprocess.run(["ip", *args], capture_output=True, text=True)
        if result.returncode != 0:
            raise OSError(f"ip {' '.join(args)}: {result.stderr.strip()}")

    def _make(self, delay_ms: float | None, loss_percent: float | None) -> None:
        for bridge in self._bridges.values():
            self._ip("netns", "add", bridge)
            self._namespaces.append(bridge)
            self._ip("-n", bridge, "link", "add", "br0", "type", "bridge")
            self._ip("-n", bridge, "link", "set", "br0", "up")
        netem = [*(["delay", f"{delay_ms}ms"] if delay_ms else []), *(["loss", f"{loss_percent}%"] if loss_percent else [])]
        refused: list[str] = []
        for name in self.names:
            ns = self.namespace(name)
            self._ip("netns", "add", ns)
            self._namespaces.append(ns)
            self._ip("-n", ns, "link", "set", "lo", "up")
            for network, dev, port, address in self._links[name]:
                bridge = self._bridges[network]
                self._ip("-n", ns, "link", "add", dev, "type", "veth", "peer", "name", port, "netns", bridge)
                self._ip("-n", ns, "addr", "add", f"{address}/24", "dev", dev)
                self._ip("-n", ns, "link", "set", dev, "up")
                self._ip("-n", bridge, "link", "set", port, "master", "br0")
                self._ip("-n", bridge, "link", "set", port, "up")
                if netem:
                    shaped = subprocess.run(["tc", "-n", ns, "qdisc", "add", "dev", dev, "root", "netem", *netem], capture_output=True, text=True)
                    if shaped.returncode != 0:
                        refused.append(shaped.stderr.strip() or "tc failed")
        if netem:
            self.shaping = f"netem {' '.join(netem)}" if not refused else f"unavailable ({refused[0]}): links are not shaped"
