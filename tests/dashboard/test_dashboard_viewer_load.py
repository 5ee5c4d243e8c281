"""What a viewer's valid login could use up, beyond sessions and streams: the server's event
loop (reading a stored run) and the queue of logins.

Before, ``/api/replay/info`` and a replay's start scanned the stored run on the event loop
(a second for two million rows): one viewer asking over and over stopped every page, stream
and login. And logins queued without bound for their scrypt check: a viewer sending its own
right password on many connections (the back-off counts failures only) kept the admin's
login waiting.
"""

from __future__ import annotations

import http.client
import json
import sqlite3
import threading
from urllib.parse import urlsplit

import pytest
from dashboard_helpers import ADMIN, VIEWER, wait_until

from cblrs.dashboard.app import DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator
from cblrs.dashboard.replay import StoreReplay
from cblrs.runtime.matcher.store import RuntimeStore

TOKEN = "run-token-of-this-test"


def _get(url: str, path: str, timeout: float, headers: dict[str, str] | None = None) -> int:
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=timeout)
    try:
        connection.request("GET", path, headers=headers or {})
        response = connection.getresponse()
        # Read to the end, a replay's stream too: a client that hangs up after the headers
        # has the server cancel the stream, under load before it reads the stored run.
        response.read()
        return response.status
    finally:
        connection.close()


@pytest.mark.parametrize(("path", "reading"), [("/api/replay/info", "info"),
                                               ("/api/replay?speed=10", "counts_before")])
def test_reading_a_stored_run_never_stops_the_server(
    wildtrack_site, serve_app, tmp_path, monkeypatch, path, reading
):
    database = tmp_path / "matcher.db"
    RuntimeStore(database).close()
    connection = sqlite3.connect(database)
    with connection:
        connection.executemany(
            "INSERT INTO tracks (frame, timestamp, track_id, x, y, camera) "
            "VALUES (?, ?, ?, ?, ?, 0)", [(i, 1_700_000_000.0 + i, i % 3, 1.0, 2.0)
                                          for i in range(20)])
    connection.close()
    entered, release = threading.Event(), threading.Event()
    slow = getattr(StoreReplay, reading)

    def stalled(self, *arguments):  # a large run: the scan takes its time
        entered.set()
        release.wait(60)
        return slow(self, *arguments)

    monkeypatch.setattr(StoreReplay, reading, stalled)
    url = serve_app(create_app(DashboardConfig(wildtrack_site, 1, database=database),
                               Authenticator(run_token=TOKEN)))
    bearer = {"Authorization": f"Bearer {TOKEN}"}
    asked = threading.Thread(target=_get, args=(url, path, 90, bearer), daemon=True)
    asked.start()
    try:
        wait_until(entered.is_set, 30, f"{path} to read the stored run")
        # while the run is read, the server answers everyone else
        assert _get(url, "/healthz", 5) == 200
        assert _get(url, "/api/status", 5, bearer) == 200
    finally:
        release.set()
        asked.join(60)


def test_one_name_from_one_address_queues_one_login_at_a_time(
    wildtrack_site, users_file, start_dashboard
):
    url = start_dashboard("--site", str(wildtrack_site), "--users", str(users_file)).url
    parts = urlsplit(url)
    start = threading.Barrier(7)
    answers: list[tuple[str, int, str]] = []

    def log_in(user: tuple[str, str]) -> None:
        connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)
        try:
            start.wait(30)
            connection.request("POST", "/api/login",
                               json.dumps({"user": user[0], "password": user[1]}),
                               {"Content-Type": "application/json",
                                "Origin": url.rstrip("/")})
            response = connection.getresponse()
            answers.append((user[0], response.status, json.loads(response.read())
                            .get("error", "")))
        finally:
            connection.close()

    threads = [threading.Thread(target=log_in, args=(VIEWER,)) for _ in range(6)]
    threads.append(threading.Thread(target=log_in, args=(ADMIN,)))
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(120)
    viewer = [(status, error) for user, status, error in answers if user == VIEWER[0]]
    assert (ADMIN[0], 200, "") in answers
    assert (200, "") in viewer
    refused = [error for status, error in viewer if status == 429]
    assert refused, f"six logins of one name at once all queued: {viewer}"
    assert set(refused) == {f"a login of {VIEWER[0]!r} from this address is under way; wait "
                            "for its answer."}
