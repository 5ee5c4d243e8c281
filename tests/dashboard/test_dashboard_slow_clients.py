"""An anonymous client cannot take the dashboard from everyone by holding connections.

Before, uvicorn kept a connection that had sent part of a request (or nothing) for as long
as the client liked: 1,100 of them, each sending a header line every 3 s, kept the
dashboard (1,024 open files, systemd's default) from answering anyone. The application under
uvicorn with the configuration `cblrs dashboard` uses, over real sockets, with short limits
to keep the test short.
"""

from __future__ import annotations

import json
import socket
import threading
import time
import urllib.request

import pytest
import uvicorn
from dashboard_helpers import wait_until

from cblrs.dashboard.app import DashboardConfig, create_app, server_config
from cblrs.dashboard.auth import Authenticator
from cblrs.dashboard.connections import connection_budget

HEADER_TIMEOUT_S = 1.0
PER_ADDRESS = 4


@pytest.fixture
def served(wildtrack_site):
    auth = Authenticator(run_token="run-token-of-this-test-0123456789")
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(64)
    config = server_config(
        create_app(DashboardConfig(wildtrack_site, 1), auth),
        request_timeout_s=HEADER_TIMEOUT_S,
        per_address=PER_ADDRESS,
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    wait_until(lambda: server.started, 30, "uvicorn to serve")
    yield listener.getsockname()[1], config.http
    server.should_exit = True
    thread.join(10)


def closed_by_server(connection: socket.socket, within_s: float) -> bool:
    """Whether the server closes ``connection`` within ``within_s`` (reads return nothing)."""
    connection.settimeout(within_s)
    try:
        return connection.recv(1024) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def healthz(port: int) -> int:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as answer:
        return answer.status


def test_a_request_whose_headers_never_end_is_closed(served):
    port, protocol = served
    trickling = socket.create_connection(("127.0.0.1", port), timeout=5)
    silent = socket.create_connection(("127.0.0.1", port), timeout=5)
    try:
        trickling.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        started = time.monotonic()
        for _ in range(4):  # a header line every 0.4 s, never the blank line
            time.sleep(0.4)
            try:
                trickling.sendall(b"X-Slow: 1\r\n")
            except OSError:
                break
        assert closed_by_server(trickling, 5.0)
        assert time.monotonic() - started < HEADER_TIMEOUT_S + 2.0
        assert closed_by_server(silent, 1.0)
        assert protocol.stats["slow"] >= 2
    finally:
        trickling.close()
        silent.close()
    assert healthz(port) == 200


def test_a_new_connection_closes_the_oldest_one_still_waiting(served):
    """Past the limit of an address, the next connection (also a legitimate client's: every
    local client is 127.0.0.1) takes the place of the oldest half-sent request."""
    port, protocol = served
    held = [socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(PER_ADDRESS)]
    try:
        for connection in held:
            connection.sendall(b"GET /healthz HTTP/1.1\r\n")  # never finished
        time.sleep(0.2)
        started = time.monotonic()
        assert healthz(port) == 200
        assert time.monotonic() - started < HEADER_TIMEOUT_S  # before any time-out
        assert closed_by_server(held[0], 0.5)  # the oldest made room
        assert protocol.stats["evicted"] >= 1
    finally:
        for connection in held:
            connection.close()


def _login_request(port: int, user: str = "nobody") -> bytes:
    body = json.dumps({"user": user, "password": "not-the-password"}).encode()
    return (
        b"POST /api/login HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nOrigin: http://127.0.0.1:%d\r\n"
        b"Content-Type: application/json\r\nContent-Length: %d\r\n\r\n%s"
        % (port, port, len(body), body)
    )


def test_when_every_connection_is_answering_a_new_one_is_closed_at_once(served):
    """Requests under way (failed logins cost about half a second of scrypt each, one at a
    time) are never cut to make room."""
    port, protocol = served
    busy = [socket.create_connection(("127.0.0.1", port), timeout=30) for _ in range(PER_ADDRESS)]
    try:
        # Each its own name: a second login of one name from one address is answered at once
        # (429), not queued behind the first.
        for index, connection in enumerate(busy):
            connection.sendall(_login_request(port, f"nobody-{index}"))
        time.sleep(0.2)
        extra = socket.create_connection(("127.0.0.1", port), timeout=5)
        try:
            assert closed_by_server(extra, 0.5)
        finally:
            extra.close()
        assert protocol.stats["refused"] >= 1
        answers = [connection.recv(4096) for connection in busy]
    finally:
        for connection in busy:
            connection.close()
    assert all(answer.startswith(b"HTTP/1.1 401") for answer in answers), answers


def test_a_request_sent_in_pieces_in_time_is_answered(served):
    """A request sent in pieces, all within the time, is answered."""
    port, _ = served
    request = _login_request(port)
    connection = socket.create_connection(("127.0.0.1", port), timeout=10)
    try:
        connection.sendall(request[:-1])
        time.sleep(0.5 * HEADER_TIMEOUT_S)
        connection.sendall(request[-1:])
        time.sleep(1.5 * HEADER_TIMEOUT_S)  # the login itself may take longer than that
        answer = connection.recv(4096)
    finally:
        connection.close()
    assert answer.startswith(b"HTTP/1.1 401"), answer[:80]


def test_the_budget_leaves_room_for_files():
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    assert 16 <= connection_budget() <= max(16, soft - 128)
