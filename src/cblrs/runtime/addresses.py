"""Network addresses: which ones stay on this machine.

A service that listens beyond loopback, or a broker whose clients come from other machines,
must not take passwords or data in clear; the checks that refuse it (the matcher's metrics
without a token, a broker configuration without TLS) ask :func:`is_loopback_host`.

Example:
    >>> is_loopback_host("127.0.0.1"), is_loopback_host("0.0.0.0")
    (True, False)
"""

from __future__ import annotations

import ipaddress
import socket


def is_loopback_host(host: str) -> bool:
    """Whether every address ``host`` names is a loopback one (``127.0.0.1``, ``::1``,
    ``localhost``); a name that does not resolve is not."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return False
    try:
        return bool(infos) and all(
            ipaddress.ip_address(str(info[4][0]).split("%")[0]).is_loopback for info in infos
        )
    except ValueError:
        return False
