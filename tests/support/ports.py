"""Free TCP ports for the tests' servers and simulators.

A port probed free with a port-0 bind can be taken before the server binds it: by another test process
(pytest-xdist workers), an outgoing connection or another port-0 bind, which all draw from the kernel's
ephemeral range (32768-60999). Here each worker takes its ports from its own block below that range, so
nothing else hands them out in between.
"""

from __future__ import annotations

import itertools
import os
import socket

FIRST, BLOCK, BLOCKS = 12000, 2000, 10
_next = itertools.count()


def free_ports(n: int = 1, host: str = "127.0.0.1") -> list[int]:
    """`n` distinct ports on `host` that nothing listens on now, from this worker's block."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    base = FIRST + BLOCK * (worker % BLOCKS)
    ports: list[int] = []
    for _ in range(BLOCK):
        if len(ports) == n:
            return ports
        port = base + next(_next) % BLOCK
        with socket.socket() as probe:
            try:
                probe.bind((host, port))
            except OSError:
                continue  # in use, or still in TIME_WAIT
        ports.append(port)
    raise RuntimeError(f"no {n} free ports in {base}-{base + BLOCK - 1} on {host}")


def free_port(host: str = "127.0.0.1") -> int:
    return free_ports(1, host)[0]


def free_port_pair(host: str = "127.0.0.1") -> int:
    """A port p of this worker's block with p + 1 free too, for a server on two adjacent ports (the ABB
    controller's motion and logger); p + 1 is then never handed out by free_ports."""
    for _ in range(BLOCK):
        port, = free_ports(1, host)
        following = port + 1
        next(_next)  # the counter's next port is `following`: it belongs to this pair (or is busy)
        if (following - FIRST) % BLOCK == 0:
            continue  # past the end of this worker's block: another worker's port
        with socket.socket() as probe:
            try:
                probe.bind((host, following))
            except OSError:
                continue
        return port
    raise RuntimeError(f"no two adjacent free ports on {host}")
