"""Network facts for tests: the machine's LAN address and who listens where (/proc/net/tcp)."""

from __future__ import annotations

import socket
from pathlib import Path


def lan_address() -> str:
    """This machine's address on its default route (what a browser on the LAN would type);
    loopback only when the machine has no other interface."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.123", 9))  # TEST-NET-1; a UDP connect sends no packet
            return s.getsockname()[0]
        except OSError:
            return "127.0.0.1"


def _tcp_sockets() -> list[tuple[str, int, str]]:
    """(local IPv4 address, local port, state hex) of every IPv4 TCP socket."""
    out = []
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        addr, hexport = fields[1].split(":")
        out.append((socket.inet_ntop(socket.AF_INET, bytes.fromhex(addr)[::-1]), int(hexport, 16), fields[3]))
    return out


def listening_addresses(port: int) -> set[str]:
    """IPv4 addresses with a socket listening on `port`."""
    return {addr for addr, p, state in _tcp_sockets() if p == port and state == "0A"}


def established_to(port: int) -> int:
    """Established connections whose server side is local `port`."""
    return sum(1 for _, p, state in _tcp_sockets() if p == port and state == "01")
