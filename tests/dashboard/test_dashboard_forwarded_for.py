"""A client cannot pick its own address with ``X-Forwarded-For``.

uvicorn trusts ``X-Forwarded-For`` from 127.0.0.1 by default, so any client on the
dashboard's machine could give each failed login another address and never meet the
per-address back-off (and write any address it liked into the log of failed logins). The
dashboard counts the address of the connection, as security.md says (behind a proxy: the
proxy's). The application under uvicorn with the configuration `cblrs dashboard` uses, over
real sockets; a back-off of 2 free failures per address to keep it short.
"""

from __future__ import annotations

import json
import socket
import threading
import urllib.error
import urllib.request

import pytest
import uvicorn
from dashboard_helpers import wait_until

from cblrs.dashboard.app import DashboardConfig, create_app, server_config
from cblrs.dashboard.auth import Authenticator, LoginLimiter


@pytest.fixture
def served(wildtrack_site):
    auth = Authenticator(run_token="run-token-of-this-test-0123456789",
                         limiter=LoginLimiter(free_per_user=100, free_per_client=2))
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    server = uvicorn.Server(server_config(create_app(DashboardConfig(wildtrack_site, 1), auth)))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [listener]}, daemon=True)
    thread.start()
    wait_until(lambda: server.started, 30, "uvicorn to serve")
    yield f"http://127.0.0.1:{listener.getsockname()[1]}/"
    server.should_exit = True
    thread.join(10)


def attempt(url: str, name: str, forwarded_for: str) -> tuple[int, dict]:
    request = urllib.request.Request(
        f"{url}api/login", method="POST",
        data=json.dumps({"user": name, "password": "guess-password-0"}).encode(),
        headers={"Content-Type": "application/json", "Origin": url.rstrip("/"),
                 "X-Forwarded-For": forwarded_for, "X-Forwarded-Proto": "https"})
    try:
        with urllib.request.urlopen(request, timeout=60) as answer:
            return answer.status, dict(answer.headers)
    except urllib.error.HTTPError as error:
        return error.code, dict(error.headers)


def test_forged_forwarded_for_does_not_escape_the_back_off(served, caplog):
    answers = [attempt(served, f"guesser{index}", f"203.0.113.{index}") for index in range(4)]
    statuses = [status for status, _ in answers]
    # two failures are free from one address, the third locks it, the fourth finds it locked
    assert statuses == [401, 401, 401, 429], statuses
    assert "203.0.113." not in caplog.text and "from 127.0.0.1" in caplog.text
    assert all("server" not in {name.lower() for name in headers} for _, headers in answers)
