"""One viewer cannot hold the dashboard's live streams by the thousand: a real `cblrs
dashboard` reading a real Mosquitto, streams opened over real sockets."""

from __future__ import annotations

import http.client
import json
from urllib.parse import urlsplit

from dashboard_helpers import ADMIN, VIEWER, wait_until

from cblrs.dashboard.app import STREAMS_PER_USER


def _login(url: str, user: tuple[str, str]) -> dict[str, str]:
    """The headers of a new session of ``user``: its cookie and its page token."""
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)
    try:
        connection.request(
            "POST",
            "/api/login",
            json.dumps({"user": user[0], "password": user[1]}),
            {"Content-Type": "application/json", "Origin": url.rstrip("/")},
        )
        response = connection.getresponse()
        answer = json.loads(response.read())
        assert response.status == 200
        return {"Cookie": response.getheader("set-cookie").split(";")[0],
                "X-CBLRS-Session": answer["session"]}
    finally:
        connection.close()


def _open_stream(url: str, session: dict[str, str]
                 ) -> tuple[int, http.client.HTTPConnection, bytes]:
    """Ask for the live stream; (status, the open connection, the body of a refusal)."""
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    connection.request("GET", "/api/stream", headers=session)
    response = connection.getresponse()
    body = b"" if response.status == 200 else response.read()
    return response.status, connection, body


def test_a_viewer_cannot_open_streams_without_limit(
    wildtrack_site, users_file, start_broker, start_dashboard
):
    broker = start_broker(cameras=["CVLab1"], matchers=["matcher1"])
    url = start_dashboard(
        "--site",
        str(wildtrack_site),
        "--users",
        str(users_file),
        "--broker",
        broker.address,
        "--username",
        "viewer",
        "--password-file",
        str(broker.password_file("viewer")),
    ).url
    viewer, again = _login(url, VIEWER), _login(url, VIEWER)  # two sessions, one user
    held = []
    try:
        for _ in range(STREAMS_PER_USER):
            status, connection, _ = _open_stream(url, viewer)
            held.append(connection)
            assert status == 200
        for session in (viewer, again):
            status, connection, body = _open_stream(url, session)
            connection.close()
            assert status == 429
            assert json.loads(body)["error"] == (
                f"{VIEWER[0]} has {STREAMS_PER_USER} live streams and replays open, the most "
                "one user may; close a page first."
            )
        status, connection, _ = _open_stream(url, _login(url, ADMIN))  # another user's own
        held.append(connection)
        assert status == 200
        held.pop(0).close()  # a page closed: its slot is free again

        def reopened() -> bool:
            status, connection, _ = _open_stream(url, again)
            held.append(connection)
            return status == 200

        wait_until(reopened, 30, "a stream once one of the viewer's pages closed")
    finally:
        for connection in held:
            connection.close()
