"""Whoever knows an admin's name cannot keep the admin out.

Failed logins lock a user name (the right password is refused during the lock). Before, the
lock held for everyone: an outsider failing for the admin's name once every 5 minutes kept
the admin from logging in for good. Now a name's lock holds only for the addresses that
failed for it. The application under uvicorn with the configuration `cblrs dashboard` uses,
over real sockets from two loopback addresses (the dashboard counts the connection's
address); a lock after 2 failures to keep it short.
"""

from __future__ import annotations

import http.client
import json
import socket
import threading

import pytest
import uvicorn
from dashboard_helpers import ADMIN, wait_until

from cblrs.dashboard.app import DashboardConfig, create_app, server_config
from cblrs.dashboard.auth import Authenticator, LoginLimiter

ATTACKER = "127.0.0.2"
OWNER = "127.0.0.3"


@pytest.fixture
def served(wildtrack_site, users_file):
    auth = Authenticator(
        users_path=users_file,
        limiter=LoginLimiter(free_per_user=2, free_per_client=100, base_s=60.0),
    )
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    server = uvicorn.Server(server_config(create_app(DashboardConfig(wildtrack_site, 1), auth)))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    wait_until(lambda: server.started, 30, "uvicorn to serve")
    yield listener.getsockname()[1]
    server.should_exit = True
    thread.join(10)


def login(port: int, source: str, password: str) -> int:
    """POST /api/login as :data:`ADMIN`'s name from ``source``; the status."""
    connection = http.client.HTTPConnection(
        "127.0.0.1", port, timeout=60, source_address=(source, 0)
    )
    try:
        connection.request(
            "POST",
            "/api/login",
            json.dumps({"user": ADMIN[0], "password": password}),
            {"Content-Type": "application/json", "Origin": f"http://127.0.0.1:{port}"},
        )
        return connection.getresponse().status
    finally:
        connection.close()


def test_an_outsider_failing_for_the_admins_name_does_not_lock_the_admin_out(served):
    statuses = [login(served, ATTACKER, "guess-password-0") for _ in range(4)]
    assert statuses[:2] == [401, 401] and statuses[-1] == 429, statuses  # the guesser waits
    assert login(served, OWNER, ADMIN[1]) == 200  # before: 429, the admin locked out
    assert login(served, ATTACKER, ADMIN[1]) == 429  # the guesser's address is still locked
