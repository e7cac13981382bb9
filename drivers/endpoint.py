"""Canonical names of the endpoints a driver connects to, so that two processes (or two cell files) naming one
controller differently still name the same thing: a host becomes its address where it resolves, always with
its port; a device path is followed to the file it names. The cell's owner locks these (cellctl/startup/ownership.py).
"""

from __future__ import annotations

import os
import socket


def address(host: str) -> str:
    """The host's first address where it resolves (so localhost is 127.0.0.1), else the name lower-cased."""
    for family in (socket.AF_INET, socket.AF_UNSPEC):  # IPv4 first: "localhost" may list ::1 first
        try:
            return socket.getaddrinfo(host, None, family, socket.SOCK_STREAM)[0][4][0]
        except (OSError, UnicodeError):  # socket.gaierror is an OSError
            continue
    return host.lower()


def tcp(host: str, port: int) -> str:
    """'tcp ADDRESS:PORT', always with the port."""
    return f"tcp {address(host)}:{port}"


def device(path: str) -> str:
    """'device /dev/ttyUSB0': the device file the path (a udev symlink, say) leads to."""
    return f"device {os.path.realpath(path)}"


def camera(identity: str) -> str:
    """A camera known by what it says it is (its serial or id), wherever it is plugged in."""
    return f"camera {identity}"
