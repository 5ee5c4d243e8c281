"""A client that opens a TLS connection to the dashboard and never finishes the handshake is
closed within seconds.

With ``--tls-cert`` the dashboard counts a connection (and applies its limits, see
`cblrs.dashboard.connections`) only once the TLS handshake is done; before, asyncio's
default handshake time-out (60 s) was the only bound on a connection that sent nothing, or
half a ClientHello, so anyone who reached the port held each of those connections for a
minute. A real `cblrs dashboard --tls-cert` process, spoken to over real sockets.
"""

from __future__ import annotations

import socket
import ssl
import time
import urllib.request
from urllib.parse import urlsplit

from dashboard_helpers import self_signed, site_copy

from cblrs.dashboard.connections import TLS_HANDSHAKE_TIMEOUT_S

CLIENT_HELLO_START = bytes.fromhex("16030100c8010000c40303")
"""The first bytes of a TLS ClientHello (record header, handshake header, version): the
server waits for the rest."""


def seconds_until_closed(connection: socket.socket, at_most_s: float) -> float | None:
    """Seconds until the server closes ``connection`` (None: still open after ``at_most_s``)."""
    start = time.monotonic()
    connection.settimeout(at_most_s)
    try:
        while connection.recv(4096):  # a server may answer before closing; read to the end
            pass
    except TimeoutError:
        return None
    except ConnectionResetError:
        pass
    return time.monotonic() - start


def test_a_tls_handshake_that_never_ends_is_closed_within_seconds(
        wildtrack_site, users_file, start_dashboard, tmp_path):
    cert, key = self_signed(tmp_path)
    site = site_copy(wildtrack_site, tmp_path / "site" / "site.yaml")
    served = start_dashboard("--site", str(site), "--users", str(users_file),
                             "--tls-cert", str(cert), "--tls-key", str(key))
    port = urlsplit(served.url).port
    silent = socket.create_connection(("127.0.0.1", port), timeout=5)
    half_hello = socket.create_connection(("127.0.0.1", port), timeout=5)
    try:
        half_hello.sendall(CLIENT_HELLO_START)
        # 60 s before (asyncio's default); now the time-out, with room for a loaded machine
        limit = TLS_HANDSHAKE_TIMEOUT_S + 10
        assert TLS_HANDSHAKE_TIMEOUT_S <= 10
        waited = [seconds_until_closed(silent, limit), seconds_until_closed(half_hello, limit)]
        assert None not in waited, f"a stalled handshake was still open after {limit} s"
    finally:
        silent.close()
        half_hello.close()
    # A genuine client still gets its answer.
    context = ssl.create_default_context(cafile=str(cert))
    with urllib.request.urlopen(f"https://127.0.0.1:{port}/healthz", timeout=30,
                                context=context) as answer:
        assert answer.status == 200
