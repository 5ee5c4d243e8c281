"""One user's logins never end another user's session: a real `cblrs dashboard` process,
logins over real sockets.

Sessions are bounded per user (``SESSIONS_PER_USER``) and in all (``MAX_SESSIONS``, both in
:mod:`cblrs.dashboard.auth`). The process is `cblrs dashboard` run by its own ``main`` with
the two lowered first (``_LAUNCH``), so a test needs a few logins, not 10,000. Before, the
table was bounded in all only and, full, ended the session idle the longest whoever held it:
here a viewer's seventh login ended the admin's session.
"""

from __future__ import annotations

import http.client
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import pytest
from dashboard_helpers import ADMIN, VIEWER, cblrs_command, stop_process

_LAUNCH = (
    "import sys\n"
    "import cblrs.dashboard.auth as auth\n"
    "auth.MAX_SESSIONS, auth.SESSIONS_PER_USER = int(sys.argv[1]), int(sys.argv[2])\n"
    "from cblrs.cli.main import main\n"
    "sys.exit(main(sys.argv[3:]))\n"
)
CAROL = ("carol", "carol-viewer-password")


@pytest.fixture
def start_limited() -> Iterator:
    """``start(most, per_user, *arguments)`` -> (base URL, the printed link)."""
    processes: list[subprocess.Popen] = []

    def start(most: int, per_user: int, *arguments: str) -> tuple[str, str]:
        process = subprocess.Popen(
            [sys.executable, "-c", _LAUNCH, str(most), str(per_user), "dashboard", "--port",
             "0", *arguments], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        processes.append(process)
        line = process.stdout.readline() if process.stdout else ""
        if not line.startswith("dashboard on "):
            process.kill()
            raise AssertionError(f"the dashboard did not start: {line}"
                                 f"{process.communicate(timeout=10)[1]}")
        link = line.split()[2]
        return link.split("login?", 1)[0], link

    yield start
    for process in processes:
        stop_process(process)


def _request(url: str, method: str, path: str, body: dict | None = None,
             headers: dict[str, str] | None = None) -> tuple[int, dict, http.client.HTTPResponse]:
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)
    try:
        sent = {"Origin": url.rstrip("/"), **(headers or {})}
        if body is not None:
            sent["Content-Type"] = "application/json"
        connection.request(method, path, None if body is None else json.dumps(body), sent)
        response = connection.getresponse()
        return response.status, json.loads(response.read() or b"{}"), response
    finally:
        connection.close()


def _login(url: str, body: dict) -> tuple[int, dict, dict[str, str]]:
    """POST /api/login: (status, answer, the new session's headers or {})."""
    status, answer, response = _request(url, "POST", "/api/login", body)
    if status != 200:
        return status, {**answer, "retry-after": response.getheader("retry-after")}, {}
    return status, answer, {"Cookie": response.getheader("set-cookie").split(";")[0],
                            "X-CBLRS-Session": answer["session"]}


def _as(user: tuple[str, str]) -> dict:
    return {"user": user[0], "password": user[1]}


def _open(url: str, session: dict[str, str]) -> bool:
    """Whether the session is still open (``/api/session`` answers it)."""
    return _request(url, "GET", "/api/session", headers=session)[0] == 200


def _add_user(users: Path, user: tuple[str, str]) -> None:
    result = subprocess.run(
        cblrs_command("dashboard-users", "add", "--users", str(users), user[0], "--role",
                      "viewer", "--password-stdin"),
        input=user[1] + "\n", capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_a_viewers_logins_never_end_the_admins_session(wildtrack_site, users_file,
                                                       start_limited):
    url, _ = start_limited(6, 3, "--site", str(wildtrack_site), "--users", str(users_file))
    status, _, admin = _login(url, _as(ADMIN))
    assert status == 200 and _open(url, admin)
    viewer = []
    for _ in range(8):  # more than the whole table holds
        status, _, session = _login(url, _as(VIEWER))
        assert status == 200
        viewer.append(session)
    assert _open(url, admin), "a viewer's logins ended the admin's session"
    # the viewer's own sessions gave way, the three it used last stay
    assert [_open(url, session) for session in viewer] == [False] * 5 + [True] * 3


def test_at_the_most_sessions_a_login_is_refused_and_no_session_ends(
    wildtrack_site, users_file, start_limited, tmp_path
):
    users = tmp_path / "users.yaml"
    users.write_bytes(users_file.read_bytes())
    users.chmod(0o600)
    _add_user(users, CAROL)
    token = subprocess.run(
        cblrs_command("dashboard-users", "token", "--users", str(users), VIEWER[0], "--label",
                      "script"), capture_output=True, text=True, timeout=60, check=True
    ).stdout.strip()
    url, _ = start_limited(4, 3, "--site", str(wildtrack_site), "--users", str(users))
    held = [_login(url, _as(VIEWER))[2] for _ in range(3)] + [_login(url, _as(CAROL))[2]]
    assert all(_open(url, session) for session in held)

    status, answer, _ = _login(url, _as(CAROL))  # a fifth: the table is full
    assert status == 503
    assert answer["error"] == ("the dashboard holds 4 sessions, the most it keeps; try again "
                               "when some have ended.")
    assert answer["retry-after"] == "60"
    assert all(_open(url, session) for session in held), "a refused login ended a session"

    status, _, again = _login(url, _as(VIEWER))  # at their own limit: replaces their own
    assert status == 200 and _open(url, again)
    assert [_open(url, session) for session in held] == [False, True, True, True]
    status, _, admin = _login(url, _as(ADMIN))  # a full table never keeps an admin out
    assert status == 200 and _open(url, admin)
    bearer = {"Authorization": f"Bearer {token}"}
    assert _request(url, "GET", "/api/status", headers=bearer)[0] == 200  # tokens hold no slot


def test_the_run_link_logs_in_past_the_limits(wildtrack_site, start_limited):
    url, link = start_limited(2, 2, "--site", str(wildtrack_site))
    token = parse_qs(urlsplit(link).query)["token"][0]
    sessions = []
    for _ in range(4):
        status, _, session = _login(url, {"token": token})
        assert status == 200
        sessions.append(session)
    assert [_open(url, session) for session in sessions] == [False, False, True, True]
    bearer = {"Authorization": f"Bearer {token}"}
    assert _request(url, "GET", "/api/status", headers=bearer)[0] == 200
