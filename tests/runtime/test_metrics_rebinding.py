"""A web page cannot read the matcher's token-less ``/metrics`` through DNS rebinding.

Without a token the metrics server binds to loopback only; a page the operator opens on that
machine can still reach it through a name of its own that it points at 127.0.0.1 (DNS
rebinding), and then read the site's cameras, lines, zones and counts. The server answers
only requests whose ``Host`` names a loopback address (421 otherwise), like the dashboard.
"""

from __future__ import annotations

import http.client

import pytest

from cblrs.runtime.matcher.metrics import MetricsServer

BODY = b'cblrs_line_crossings_total{line="gate"} 3\n'


@pytest.fixture(scope="module")
def server():
    started = MetricsServer(("127.0.0.1", 0), lambda: BODY, lambda: (True, ""),
                            lambda: (True, "")).start()
    yield started
    started.close()


def get(server: MetricsServer, path: str, host: str) -> tuple[int, bytes]:
    connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    try:
        connection.putrequest("GET", path, skip_host=True)
        connection.putheader("Host", host)
        connection.endheaders()
        answer = connection.getresponse()
        return answer.status, answer.read()
    finally:
        connection.close()


@pytest.mark.parametrize("path", ["/metrics", "/healthz", "/readyz"])
def test_a_rebound_host_name_is_refused(server, path):
    for host in (f"evil.example:{server.port}", "evil.example", f"127.0.0.1.evil.example:"
                 f"{server.port}", "", f"[::ffff:8.8.8.8]:{server.port}"):
        status, body = get(server, path, host)
        assert status == 421, (host, status)
        assert b"gate" not in body


def test_loopback_host_names_are_answered(server):
    for host in (f"127.0.0.1:{server.port}", f"localhost:{server.port}", "127.0.0.1",
                 f"[::1]:{server.port}", f"metrics.localhost:{server.port}"):
        assert get(server, "/metrics", host) == (200, BODY), host
