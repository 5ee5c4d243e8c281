"""Idle connections cannot take the matcher's metrics server (or the matcher) down.

The server started a thread per connection and waited for its request forever: anyone who
reaches the port (beyond loopback it answers the network, token or not) could open
connections and send nothing until the matcher ran out of threads. Now a connection that
says nothing for ``idle_timeout_s`` is closed, and past ``max_connections`` open ones a new
connection is closed at once; scrapes go on.
"""

from __future__ import annotations

import socket
import time
import urllib.request

import pytest

from cblrs.runtime.matcher.metrics import MetricsServer

TOKEN = "s3cret-metrics-token-0123456789"


@pytest.fixture(scope="module")
def server():
    started = MetricsServer(("127.0.0.1", 0), lambda: b"cblrs_live_tracks 3\n",
                            lambda: (True, ""), lambda: (True, ""), token=TOKEN,
                            idle_timeout_s=0.5, max_connections=4).start()
    yield started
    started.close()


def closed_by_server(connection: socket.socket, within_s: float) -> bool:
    connection.settimeout(within_s)
    try:
        return connection.recv(1024) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def test_idle_connections_are_closed_and_scrapes_go_on(server):
    idle = [socket.create_connection(("127.0.0.1", server.port), timeout=5)
            for _ in range(12)]
    try:
        started = time.monotonic()
        assert all(closed_by_server(connection, 5.0) for connection in idle)
        assert time.monotonic() - started < 4.0
        request = urllib.request.Request(f"{server.url}/metrics",
                                         headers={"Authorization": f"Bearer {TOKEN}"})
        with urllib.request.urlopen(request, timeout=5) as answer:
            assert answer.status == 200 and b"cblrs_live_tracks 3" in answer.read()
    finally:
        for connection in idle:
            connection.close()


def test_past_the_limit_a_new_connection_is_closed_at_once(server):
    idle = [socket.create_connection(("127.0.0.1", server.port), timeout=5)
            for _ in range(4)]
    try:
        time.sleep(0.1)  # the four are being served (waiting for their requests)
        extra = socket.create_connection(("127.0.0.1", server.port), timeout=5)
        try:
            assert closed_by_server(extra, 0.3)  # well before the idle time-out
        finally:
            extra.close()
    finally:
        for connection in idle:
            connection.close()
