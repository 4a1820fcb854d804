"""Local TCP addresses for the daemons the benchmarks start."""

from __future__ import annotations

import socket


def free_ports(n: int) -> list[int]:
    """n distinct free TCP ports (all held while choosing: one at a time, the kernel can hand
    out the same port twice, and serve then refuses pub == control)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]
    finally:
        for s in socks:
            s.close()


def local_addresses(n: int) -> list[str]:
    """n distinct ``tcp://127.0.0.1:port`` addresses (a daemon's pub and control sockets)."""
    return [f"tcp://127.0.0.1:{p}" for p in free_ports(n)]
