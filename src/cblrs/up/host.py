"""What this host offers a run of ``cblrs up``: whether a port can be listened on, and the
Mosquitto binary (Debian installs it outside an ordinary user's PATH)."""

from __future__ import annotations

import os
import shutil
import socket
from pathlib import Path


def port_is_free(port: int, host: str = "127.0.0.1") -> bool:
    """Whether ``host:port`` can be bound now by a server: as Mosquitto, nats-server and
    uvicorn bind (``SO_REUSEADDR``), so the connections a stopped run left in TIME_WAIT
    (a minute after its broker or dashboard closed them) do not count, only a listener."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


def find_broker(path: str | None = None) -> str | None:
    """The mosquitto binary on the PATH (``path``, default the environment's), or in the
    system's sbin folders when the PATH is a user's ordinary one (Debian installs it in
    /usr/sbin, outside a user's PATH); None when there is none."""
    path = os.environ.get("PATH", "") if path is None else path
    found = shutil.which("mosquitto", path=path)
    if found:
        return found
    folders = path.split(os.pathsep)
    if "/usr/bin" in folders:
        for folder in ("/usr/local/sbin", "/usr/sbin", "/sbin"):
            candidate = Path(folder) / "mosquitto"
            if folder not in folders and candidate.is_file() and os.access(candidate, os.X_OK):
                return str(candidate)
    return None
