"""Network namespaces as hosts (``ip netns``): each gets a veth pair with a /30 of
10.231.0.0/24, the host side on this machine, and its commands run with their own
hostname (``unshare --uts``). Traffic only flows between a namespace and this
machine: no routes, no forwarding. :meth:`Hosts.close` deletes every namespace
(and so its veth pair) even after a failure."""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass

SUBNET = "10.231.0."


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


def unavailable() -> str | None:
    """Why namespaces cannot be made here (None when they can)."""
    if os.geteuid() != 0:
        return "needs root for ip netns"
    if shutil.which("ip") is None or shutil.which("unshare") is None:
        return "needs the ip and unshare commands"
    if SUBNET in _ip("-4", "addr", check=False).stdout:
        return f"{SUBNET}0/24 is already in use on this machine"
    probe = f"svrprobe{os.getpid() % 100000}"
    out = _ip("netns", "add", probe, check=False)
    if out.returncode != 0:
        return f"ip netns add failed: {out.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


@dataclass
class Host:
    name: str  # the namespace and the hostname
    address: str  # inside the namespace
    gateway: str  # this machine's end of the veth pair

    def wrap(self, argv: list[str]) -> list[str]:
        """``argv`` run in the namespace with the host's hostname (same process: execs)."""
        return [
            "ip", "netns", "exec", self.name,
            "unshare", "--uts", "--",
            "sh", "-c", 'hostname "$0" && exec "$@"', self.name, *argv,
        ]  # fmt: skip


class Hosts:
    def __init__(self):
        self.hosts: list[Host] = []
        self.tag = f"{os.getpid() % 10000}"

    def add(self, label: str) -> Host:
        i = len(self.hosts)
        assert i < 60
        ns = f"svr{self.tag}{label}"[:15]
        outside, inside = f"sv{self.tag}h{i}", f"sv{self.tag}n{i}"
        gw, addr = f"{SUBNET}{4 * i + 1}", f"{SUBNET}{4 * i + 2}"
        host = Host(ns, addr, gw)
        self.hosts.append(host)  # before anything can fail: close() removes it
        _ip("netns", "add", ns)
        _ip("link", "add", outside, "type", "veth", "peer", "name", inside)
        _ip("link", "set", inside, "netns", ns)
        _ip("addr", "add", f"{gw}/30", "dev", outside)
        _ip("link", "set", outside, "up")
        _ip("-n", ns, "addr", "add", f"{addr}/30", "dev", inside)
        _ip("-n", ns, "link", "set", inside, "up")
        _ip("-n", ns, "link", "set", "lo", "up")
        return host

    def close(self) -> None:
        for i, h in enumerate(self.hosts):
            _ip("netns", "del", h.name, check=False)  # its veth pair goes with it
            _ip("link", "del", f"sv{self.tag}h{i}", check=False)
        self.hosts.clear()
