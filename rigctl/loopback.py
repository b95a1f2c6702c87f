"""Loopback addresses and ports for a simulated rig, so two suites (or a suite and a
benchmark) can share a host.

The UR protocols fix their ports (RTDE 30004, dashboard 29999, script 30003), so each
simulated controller gets its own address in 127.0.0.0/8 instead; everything else binds
an ephemeral port.
"""

from __future__ import annotations

import os
import random
import socket

UR_PORTS = (30004, 29999, 30003, 30002)
_rng = random.Random(os.getpid() ^ int.from_bytes(os.urandom(4), "little"))


def _free(host: str, ports: tuple[int, ...]) -> bool:
    for port in ports:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind((host, port))
            except OSError:
                return False
    return True


def free_host() -> str:
    """A random 127.a.b.c (a >= 20) whose UR ports are all free right now."""
    for _ in range(200):
        host = f"127.{_rng.randint(20, 250)}.{_rng.randint(0, 255)}.{_rng.randint(2, 254)}"
        if _free(host, UR_PORTS):
            return host
    raise RuntimeError("no free loopback address for a simulated controller")


def free_port(host: str = "127.0.0.1") -> int:
    """An ephemeral TCP port on ``host`` that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return sock.getsockname()[1]
