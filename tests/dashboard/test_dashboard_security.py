"""The dashboard's HTTP side attacked as an outsider would: a real `cblrs dashboard` (uvicorn,
in its own process) with a users file, spoken to over real sockets.

Anonymous requests, a viewer saving, cross-site writes (another origin, ``text/plain``,
forms, no page token), the session cookie without its page token, a forged Host (DNS
rebinding), a non-loopback bind without users, and the legitimate admin save with the
session's cookie and page token. Session expiry and the login
back-off are tested in-process with a clock the test moves (no test waits on a timer).
"""

from __future__ import annotations

import http.client
import json
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest
import yaml
from dashboard_helpers import (
    ADMIN,
    VIEWER,
    calibration_points,
    cblrs_command,
    first_headers,
    self_signed,
    site_copy,
    stop_process,
)

from cblrs.cli.main import main
from cblrs.dashboard.app import STATIC, DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator, LoginLimiter, LoginRefused
from cblrs.dashboard.users import Role
from cblrs.site import load_site

EVIL = "http://evil.example"


def call(url: str, path: str, method: str = "GET", headers: dict | None = None,
         body: bytes | str | None = None) -> tuple[int, dict[str, str], bytes]:
    """One request, no redirect followed: (status, lower-cased headers, body)."""
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)
    try:
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        data = response.read()
        return response.status, first_headers(response), data
    finally:
        connection.close()


def origin(url: str) -> str:
    return url.rstrip("/")


def other_port(url: str) -> str:
    """The origin of the same scheme and host on another port (never this one)."""
    parts = urlsplit(url)
    port = parts.port + 1 if parts.port < 65535 else parts.port - 1
    return f"{parts.scheme}://{parts.hostname}:{port}"


class Browser:
    """A logged-in client: the session cookie and the page token the login answered."""

    def __init__(self, url: str, user: tuple[str, str]):
        self.url = url
        status, headers, body = call(url, "/api/login", "POST", {
            "Content-Type": "application/json", "Origin": origin(url)},
            json.dumps({"user": user[0], "password": user[1]}))
        assert status == 200, body
        self.set_cookie = headers["set-cookie"]
        self.cookie = self.set_cookie.split(";")[0]
        self.token = json.loads(body)["session"]
        self.headers = {"Cookie": self.cookie, "X-CBLRS-Session": self.token}
        status, _, body = call(url, "/api/session", headers=self.headers)
        assert status == 200, body
        self.session = json.loads(body)

    def get(self, path: str, token: str | None = "session") -> tuple[int, dict[str, str], bytes]:
        return call(self.url, path, headers=self.with_token(token))

    def with_token(self, token: str | None) -> dict[str, str]:
        """The cookie, and the page token (``"session"``: the login's; None: none)."""
        headers = {"Cookie": self.cookie}
        if token is not None:
            headers["X-CBLRS-Session"] = self.token if token == "session" else token
        return headers

    def post(self, path: str, body: str, content_type: str = "application/json",
             origin_header: str | None = "same", token: str | None = "session",
             referer: str | None = None) -> tuple[int, dict[str, str], bytes]:
        headers = {**self.with_token(token), "Content-Type": content_type}
        if origin_header is not None:
            headers["Origin"] = origin(self.url) if origin_header == "same" else origin_header
        if referer is not None:
            headers["Referer"] = referer
        return call(self.url, path, "POST", headers, body)


@pytest.fixture
def own_site(wildtrack_site, tmp_path) -> Path:
    """A copy of the WILDTRACK site that this test may rewrite."""
    return site_copy(wildtrack_site, tmp_path / "site" / "site.yaml")


@pytest.fixture
def dashboard(own_site, users_file, start_dashboard, tmp_path) -> str:
    """A dashboard of its own (for a test that saves)."""
    return start_dashboard("--site", str(own_site), "--users", str(users_file),
                           "--references", str(tmp_path / "references")).url


@pytest.fixture(scope="module")
def shared(wildtrack_site, users_file, tmp_path_factory) -> Iterator[str]:
    """One dashboard for the tests that change nothing but sessions (each logs in anew;
    failed logins use names of their own, so that no lock reaches the others)."""
    folder = tmp_path_factory.mktemp("shared")
    process = subprocess.Popen(
        cblrs_command("dashboard", "--port", "0", "--site", str(wildtrack_site), "--users",
                      str(users_file), "--references", str(folder / "references")),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = process.stdout.readline() if process.stdout else ""
        assert line.startswith("dashboard on "), line + (process.stderr.read()
                                                        if process.stderr else "")
        yield line.split()[2]
    finally:
        stop_process(process)


PAGES = ["/", "/calibrate"]
API = ["/api/site", "/api/status", "/api/stream", "/api/replay/info", "/api/replay", "/map",
       "/api/session", "/api/calibrate/cameras", "/api/calibrate/frame/CVLab1",
       "/api/calibrate/reference/CVLab1", "/api/places"]


def test_anonymous_requests_are_refused(shared, wildtrack_site):
    dashboard, own_site = shared, wildtrack_site
    for path in PAGES:
        status, headers, _ = call(dashboard, path)
        assert status == 303 and headers["location"].startswith("/login?next="), path
    for path in API:
        status, _, body = call(dashboard, path)
        assert status == 401 and b"log in" in body, path
    before = own_site.read_bytes()
    body = json.dumps(calibration_points(own_site))
    for path in ("/api/calibrate/save", "/api/calibrate/fit", "/api/places/save", "/api/logout"):
        status, _, _ = call(dashboard, path, "POST", {"Content-Type": "application/json",
                                                      "Origin": origin(dashboard)}, body)
        assert status == 401, path
    assert own_site.read_bytes() == before
    # Open: the login page, the health check and the page's static files (no data).
    for path in ("/login", "/healthz", "/static/dashboard.js", "/static/login.js"):
        assert call(dashboard, path)[0] == 200, path
    # A wrong password and an unknown user get the same answer.
    for user, password in ((ADMIN[0], "not-the-password"), ("mallory", "any-password-1")):
        status, _, body = call(dashboard, "/api/login", "POST", {
            "Content-Type": "application/json", "Origin": origin(dashboard)},
            json.dumps({"user": user, "password": password}))
        assert status == 401 and json.loads(body)["error"] == "wrong user name or password."


def test_every_answer_carries_the_security_headers(shared):
    dashboard = shared
    viewer = Browser(dashboard, VIEWER)
    answers = [call(dashboard, path) for path in ("/", "/login", "/static/dashboard.js",
                                                   "/api/site", "/healthz")]
    answers.append(viewer.get("/api/site"))
    answers.append(viewer.get("/"))
    for _, headers, _ in answers:
        policy = headers["content-security-policy"]
        assert "script-src 'self';" in policy and "frame-ancestors 'none'" in policy, policy
        assert "unsafe-inline" not in policy and "unsafe-eval" not in policy
        assert "default-src 'none'" in policy
        assert headers["x-content-type-options"] == "nosniff"
        assert headers["referrer-policy"] == "same-origin"
        assert headers["x-frame-options"] == "DENY"
    assert answers[-2][1]["cache-control"] == "no-store"  # positions are not cached


def test_the_page_code_never_writes_html():
    """The pages have no inline script, handler or style for the policy to allow, and their
    scripts never turn data into HTML (names go in as text)."""
    pages = sorted(STATIC.glob("*.html"))
    assert {page.name for page in pages} >= {"index.html", "calibrate.html", "login.html"}
    for page in pages:
        text = page.read_text()
        assert not re.search(r"<script(?![^>]*\bsrc=)", text), page.name
        assert not re.search(r"<[^>]*\son[a-z]+\s*=", text), page.name
        assert "style=" not in text and "javascript:" not in text, page.name
    scripts = sorted(STATIC.glob("*.js"))
    assert len(scripts) >= 4
    for script in scripts:
        text = script.read_text()
        for sink in ("innerHTML", "outerHTML", "insertAdjacentHTML", "document.write", "eval(",
                     "new Function", "setAttribute(\"on"):
            assert sink not in text, (script.name, sink)


def test_session_cookie_flags_roles_and_logout(shared, wildtrack_site):
    dashboard, own_site = shared, wildtrack_site
    viewer = Browser(dashboard, VIEWER)
    flags = [part.strip().lower() for part in viewer.set_cookie.split(";")]
    assert "httponly" in flags and "samesite=strict" in flags and "path=/" in flags
    assert "secure" not in flags  # plain HTTP on loopback; over TLS the cookie is Secure
    assert viewer.session == {"user": VIEWER[0], "role": "viewer", "via": "session"}
    assert len(viewer.token) >= 32 and viewer.token not in viewer.cookie
    assert viewer.get("/api/site")[0] == 200
    assert viewer.get("/")[0] == 200
    # The cookie alone (or with another token) is nobody for the API; the pages (static
    # shells) answer it as they answer any cookie, a made-up one too (nothing about the
    # session: tests/dashboard/test_dashboard_pages_cookie_browser.py).
    for token in (None, "x" * 43, viewer.cookie.split("=", 1)[1]):
        for path in API:
            status, _, body = viewer.get(path, token)
            assert status == 401 and b"X-CBLRS-Session" in body, (path, token)
    forged = {"Cookie": viewer.cookie.split("=", 1)[0] + "=" + "x" * 43}
    for path in PAGES:
        assert viewer.get(path, None)[::2] == call(dashboard, path, headers=forged)[::2], path
    # A viewer sees, and cannot calibrate: 403 even with the token, same origin, JSON.
    before = own_site.read_bytes()
    status, _, body = viewer.post("/api/calibrate/save", json.dumps(calibration_points(own_site)))
    assert status == 403 and "needs an admin" in json.loads(body)["error"]
    assert viewer.get("/api/calibrate/cameras")[0] == 403
    assert viewer.get("/api/calibrate/frame/CVLab1")[0] == 403
    assert own_site.read_bytes() == before
    # Logging out needs the token too, and ends the session for good.
    assert viewer.post("/api/logout", "{}", token=None)[0] == 401
    status, headers, _ = viewer.post("/api/logout", "{}")
    assert status == 200 and "max-age=0" in headers["set-cookie"].lower()
    assert viewer.get("/api/site")[0] == 401
    assert call(dashboard, "/")[0] == 303  # the browser dropped the cookie (max-age=0)


def test_cross_site_writes_are_refused_and_the_admin_saves(dashboard, own_site, tmp_path):
    admin = Browser(dashboard, ADMIN)
    assert admin.session["role"] == "admin"
    request = calibration_points(own_site)
    body = json.dumps(request)
    before = own_site.read_bytes()
    save = "/api/calibrate/save"
    refused = [
        # (what, response, expected status, words of the sentence)
        ("the issue's attack: text/plain from another origin",
         admin.post(save, body, "text/plain", origin_header=EVIL), 403, "another site"),
        ("text/plain from the same origin", admin.post(save, body, "text/plain"), 415,
         "application/json"),
        ("a form", admin.post(save, "camera=CVLab1", "application/x-www-form-urlencoded"),
         415, "application/json"),
        ("a multipart form", admin.post(save, "--x--", "multipart/form-data; boundary=x"),
         415, "application/json"),
        ("JSON from another origin", admin.post(save, body, origin_header=EVIL), 403,
         "another site"),
        ("JSON referred by another site", admin.post(save, body, origin_header=None,
                                                     referer=f"{EVIL}/page"), 403,
         "another site"),
        ("JSON without Origin or Referer", admin.post(save, body, origin_header=None), 403,
         "without Origin"),
        ("JSON without the page token", admin.post(save, body, token=None), 401,
         "X-CBLRS-Session"),
        ("JSON with another token", admin.post(save, body, token="x" * 43), 401,
         "X-CBLRS-Session"),
        ("an origin of the same host on another port",
         admin.post(save, body, origin_header=other_port(dashboard)), 403,
         "another site"),
    ]
    for what, (status, _, answer), expected, words in refused:
        assert status == expected, (what, status, answer)
        assert words in json.loads(answer)["error"], (what, answer)
        assert own_site.read_bytes() == before, what
    assert not (tmp_path / "references" / "CVLab1.png").exists()
    # The admin, same origin, JSON, with the session's token: saved and rendered.
    status, _, answer = admin.post(save, body)
    assert status == 200, answer
    saved = load_site(own_site).model.cameras[0]
    assert saved.name == "CVLab1" and saved.geometry == "points" and len(saved.points) == 8
    assert (tmp_path / "references" / "CVLab1.png").is_file()


def test_api_tokens_and_users_file_changes(own_site, users_file, start_dashboard, tmp_path):
    users = tmp_path / "users.yaml"
    shutil.copyfile(users_file, users)
    users.chmod(0o600)
    result = subprocess.run(cblrs_command("dashboard-users", "token", "--users", str(users),
                                          ADMIN[0], "--label", "script"),
                            capture_output=True, text=True, timeout=60)
    token = result.stdout.strip()
    url = start_dashboard("--site", str(own_site), "--users", str(users)).url
    bearer = {"Authorization": f"Bearer {token}"}
    status, _, body = call(url, "/api/session", headers=bearer)
    assert status == 200 and json.loads(body) == {"user": ADMIN[0], "role": "admin",
                                                  "via": "token"}
    assert call(url, "/api/session", headers={"Authorization": f"Bearer {token}x"})[0] == 401
    # A script with a token needs no session page token (no browser sends it on its own), but
    # still JSON, and never from another origin.
    json_type = {**bearer, "Content-Type": "application/json"}
    status, _, body = call(url, "/api/calibrate/fit", "POST", json_type, json.dumps(
        {"camera": "CVLab1", "image_size": [1920, 1080], "points": []}))
    assert status == 422 and "4" in json.loads(body)["error"]  # reached the fit
    assert call(url, "/api/calibrate/fit", "POST", {**json_type, "Origin": EVIL}, "{}")[0] == 403
    assert call(url, "/api/calibrate/fit", "POST", {**bearer, "Content-Type": "text/plain"},
                "{}")[0] == 415
    # Changing a user in the file ends their sessions and tokens at once.
    viewer = Browser(url, VIEWER)
    assert viewer.get("/api/site")[0] == 200
    result = subprocess.run(cblrs_command("dashboard-users", "passwd", "--users", str(users),
                                          VIEWER[0], "--password-stdin"),
                            input="a-new-password-1\n", capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert viewer.get("/api/site")[0] == 401
    assert Browser(url, (VIEWER[0], "a-new-password-1")).get("/api/site")[0] == 200
    subprocess.run(cblrs_command("dashboard-users", "revoke", "--users", str(users), ADMIN[0],
                                 "--label", "script"), check=True, capture_output=True,
                   timeout=60)
    assert call(url, "/api/session", headers=bearer)[0] == 401


def test_failed_logins_back_off(shared):
    """Wrong passwords for one name: after five, each failure locks the name for twice as
    long as the previous one; some attempt soon meets the lock (429 with Retry-After)."""
    headers = {"Content-Type": "application/json", "Origin": origin(shared)}
    wrong = json.dumps({"user": "trudy", "password": "guess-password-0"})
    statuses = []
    for _ in range(12):
        status, answer_headers, body = call(shared, "/api/login", "POST", headers, wrong)
        statuses.append(status)
        if status == 429:
            assert int(answer_headers["retry-after"]) >= 1
            assert "too many failed logins" in json.loads(body)["error"]
            break
    assert statuses[:5] == [401] * 5 and statuses[-1] == 429, statuses


def test_login_back_off_and_session_expiry_in_process(wildtrack_site, users_file, tmp_path):
    from starlette.testclient import TestClient

    now = [1000.0]
    limiter = LoginLimiter(free_per_user=2, free_per_client=100, base_s=1.0, max_s=8.0,
                           clock=lambda: now[0])
    for _ in range(2):
        limiter.failed("bob", "1.2.3.4")
    assert limiter.wait_s("bob", "1.2.3.4") == 0
    waits = []
    for _ in range(5):
        limiter.failed("bob", "1.2.3.4")
        waits.append(limiter.wait_s("bob", "1.2.3.4"))
    assert waits == [1.0, 2.0, 4.0, 8.0, 8.0]
    assert limiter.wait_s("alice", "5.6.7.8") == 0  # other names, other clients: free
    assert limiter.wait_s("bob", "5.6.7.8") == 0  # bob's lock holds where bob failed only
    limiter.succeeded("bob", "1.2.3.4")
    assert limiter.wait_s("bob", "1.2.3.4") == 0
    limiter.failed("bob", "1.2.3.4")  # bob's count stays: the next failure locks again
    assert limiter.wait_s("bob", "1.2.3.4") == 8.0
    now[0] += 2 * 8.0 + 1  # quiet for twice the longest lock: bob's count is forgotten
    limiter.failed("bob", "1.2.3.4")
    assert limiter.wait_s("bob", "1.2.3.4") == 0

    auth = Authenticator(users_path=users_file, session_s=100.0, idle_s=30.0,
                         clock=lambda: now[0],
                         limiter=LoginLimiter(free_per_user=1, clock=lambda: now[0]))
    # During a lock even the right password is refused; after it, it is accepted.
    for _ in range(2):
        with pytest.raises(LoginRefused) as refused:
            auth.login(VIEWER[0], "wrong-password-x", "9.9.9.9")
        assert refused.value.status == 401
    with pytest.raises(LoginRefused) as refused:
        auth.login(VIEWER[0], VIEWER[1], "9.9.9.9")
    assert refused.value.status == 429
    assert "try again in 1 s" in str(refused.value)
    now[0] += 1.5
    assert auth.login(VIEWER[0], VIEWER[1], "9.9.9.9").role == Role.VIEWER

    app = create_app(DashboardConfig(wildtrack_site, 1, references=tmp_path / "r"), auth)
    client = TestClient(app, base_url="http://127.0.0.1")
    origin_header = {"Origin": "http://127.0.0.1"}

    def log_in() -> None:
        answer = client.post("/api/login", json={"user": VIEWER[0], "password": VIEWER[1]},
                             headers=origin_header)
        assert answer.status_code == 200
        client.headers["X-CBLRS-Session"] = answer.json()["session"]

    log_in()
    assert client.get("/api/site").status_code == 200
    now[0] += 31.0  # idle too long
    assert client.get("/api/site").status_code == 401
    log_in()
    for _ in range(4):  # requests keep it alive ...
        now[0] += 25.0
        assert client.get("/api/site").status_code == 200
    now[0] += 25.0  # ... until its lifetime is over
    assert client.get("/api/site").status_code == 401


def test_forged_host_is_refused_on_loopback(shared):
    """DNS rebinding: a name the attacker controls pointing at 127.0.0.1."""
    dashboard = shared
    port = urlsplit(dashboard).port
    status, _, body = call(dashboard, "/login", headers={"Host": f"evil.example:{port}"})
    assert status == 421 and b"not served here" in body
    for host in (f"localhost:{port}", f"127.0.0.1:{port}"):
        assert call(dashboard, "/login", headers={"Host": host})[0] == 200


def test_binding_beyond_loopback_needs_users(own_site, users_file, capsys):
    assert main(["dashboard", "--site", str(own_site), "--host", "0.0.0.0", "--port", "0"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "needs --users FILE" in lines[0]
    for extra, words in ((["--tls-cert", str(own_site)], "together"),
                         (["--origin", "evil"], "scheme and host")):
        assert main(["dashboard", "--site", str(own_site), "--users", str(users_file),
                     "--port", "0", *extra]) == 2
        assert words in capsys.readouterr().err


def test_binding_beyond_loopback_with_users_warns_without_tls(own_site, users_file,
                                                             start_dashboard):
    served = start_dashboard("--site", str(own_site), "--users", str(users_file), "--host",
                             "0.0.0.0")
    assert "token=" not in served.link
    port = urlsplit(served.url).port
    assert call(f"http://127.0.0.1:{port}/", "/api/site")[0] == 401
    served.process.terminate()
    _, error = served.process.communicate(timeout=30)
    assert "cross the network in clear" in error


def test_without_users_the_run_link_is_the_only_way_in(own_site, start_dashboard):
    served = start_dashboard("--site", str(own_site))
    assert "/login?token=" in served.link
    token = served.link.split("token=", 1)[1]
    assert call(served.url, "/api/site")[0] == 401
    assert call(served.url, "/login?token=" + "x" * len(token))[0] == 401
    # The link's page opens no session itself: its script posts the token (the browser test
    # is in test_dashboard_redirect_browser.py); the answer holds the page token.
    status, headers, _ = call(served.url, "/login?token=" + token)
    assert status == 200 and "set-cookie" not in headers
    json_type = {"Content-Type": "application/json", "Origin": origin(served.url)}
    status, _, body = call(served.url, "/api/login", "POST", json_type,
                           json.dumps({"token": "x" * len(token)}))
    assert status == 401 and "login link is not valid" in json.loads(body)["error"]
    status, headers, body = call(served.url, "/api/login", "POST", json_type,
                                 json.dumps({"token": token}))
    assert status == 200
    session = {"Cookie": headers["set-cookie"].split(";")[0],
               "X-CBLRS-Session": json.loads(body)["session"]}
    status, _, body = call(served.url, "/api/session", headers=session)
    assert status == 200 and json.loads(body)["role"] == "admin"
    assert call(served.url, "/api/session", headers={"Cookie": session["Cookie"]})[0] == 401
    # The run's token is also the admin's API token (scripts).
    status, _, body = call(served.url, "/api/session",
                           headers={"Authorization": f"Bearer {token}"})
    assert status == 200 and json.loads(body)["via"] == "token"
    status, _, body = call(served.url, "/api/login", "POST", {
        "Content-Type": "application/json", "Origin": origin(served.url)},
        json.dumps({"user": "admin", "password": "any-password-1"}))
    assert status == 401 and "login link" in json.loads(body)["error"]


def test_hostile_names_in_the_site_file_are_refused(own_site, tmp_path, capsys):
    payload = '<img src=x onerror="document.title=\'PWNED\'">'
    document = yaml.safe_load(own_site.read_text())
    points = [{"name": payload if index == 0 else f"p{index}", "u": u, "v": v, "x": x, "y": y}
              for index, (u, v, x, y) in enumerate([(100.0, 900.0, 0.0, 0.0),
                                                    (1800.0, 900.0, 5.0, 0.0),
                                                    (1700.0, 400.0, 5.0, 10.0),
                                                    (200.0, 400.0, 0.0, 10.0)])]
    cases = {
        "zone": lambda d: d["places"]["zones"][0].update(name=payload),
        "line": lambda d: d["places"]["lines"][0].update(name=payload),
        "site": lambda d: d.update(name=payload),
        "point": lambda d: d["cameras"].__setitem__(0, {
            "name": "CVLab1", "image_size": [1920, 1080], "points": points}),
    }
    for what, change in cases.items():
        copy = json.loads(json.dumps(document))
        change(copy)
        path = tmp_path / f"{what}.yaml"
        path.write_text(yaml.safe_dump(copy, sort_keys=False))
        assert main(["site", "check", str(path)]) != 0
        captured = capsys.readouterr()
        assert "may not contain '<'" in captured.out + captured.err, (what, captured)
        assert main(["dashboard", "--site", str(path), "--port", "0"]) == 1
        error = capsys.readouterr().err
        assert "may not contain '<'" in error and len(error.strip().splitlines()) == 1, what


def test_over_tls_the_cookie_is_secure(own_site, users_file, start_dashboard, tmp_path):
    import ssl

    cert, key = self_signed(tmp_path)
    served = start_dashboard("--site", str(own_site), "--users", str(users_file),
                             "--tls-cert", str(cert), "--tls-key", str(key))
    assert served.url.startswith("https://127.0.0.1:")
    port = urlsplit(served.url).port
    context = ssl.create_default_context(cafile=str(cert))
    set_cookies: list[str] = []  # every Set-Cookie of the last answer

    def tls_call(path: str, method: str = "GET", headers: dict | None = None,
                 body: str | None = None) -> tuple[int, dict[str, str], bytes]:
        connection = http.client.HTTPSConnection("127.0.0.1", port, timeout=120,
                                                 context=context)
        try:
            connection.request(method, path, body=body, headers=headers or {})
            response = connection.getresponse()
            set_cookies[:] = response.msg.get_all("set-cookie") or []
            return response.status, first_headers(response), response.read()
        finally:
            connection.close()

    https_origin = f"https://127.0.0.1:{port}"
    status, headers, body = tls_call("/api/login", "POST", {
        "Content-Type": "application/json", "Origin": https_origin},
        json.dumps({"user": VIEWER[0], "password": VIEWER[1]}))
    assert status == 200
    token = json.loads(body)["session"]
    cookie = headers["set-cookie"]
    flags = [part.strip().lower() for part in cookie.split(";")]
    assert cookie.startswith("__Host-cblrs_session=") and "secure" in flags
    assert "httponly" in flags and "samesite=strict" in flags
    device = [value for value in set_cookies if value.startswith("__Host-cblrs_device=")]
    assert len(device) == 1, set_cookies  # the browser's device cookie, as guarded
    device_flags = [part.strip().lower() for part in device[0].split(";")]
    assert {"secure", "httponly", "samesite=strict", "path=/"} <= set(device_flags)
    session = {"Cookie": cookie.split(";")[0], "X-CBLRS-Session": token}
    assert tls_call("/api/site", headers=session)[0] == 200
    assert tls_call("/api/site", headers={"Cookie": session["Cookie"]})[0] == 401
    # The same host and port over plain HTTP is another origin.
    status, _, _ = tls_call("/api/logout", "POST", {
        **session, "Content-Type": "application/json",
        "Origin": f"http://127.0.0.1:{port}"}, "{}")
    assert status == 403
    with pytest.raises((http.client.HTTPException, ConnectionError, OSError)):
        call(f"http://127.0.0.1:{port}/", "/api/site")  # no clear text on the TLS port


def test_a_viewer_never_learns_the_servers_paths(own_site, users_file, start_dashboard,
                                                 wildtrack_root, tmp_path):
    """The answers a viewer reads name the stored run by its file name, not by where it lies
    on the server (before: /api/status, /api/replay/info, the replay's first message and its
    refusals gave the database's absolute path)."""
    from cblrs.datasets import load_scene
    from cblrs.runtime.matcher.store import RuntimeStore

    folder = tmp_path / "private-state-folder"
    folder.mkdir()
    database, empty = folder / "plane1.db", folder / "empty.db"
    rows = load_scene(wildtrack_root).ground_truth
    rows = rows[rows.timestamp == rows.timestamp.min()]
    store = RuntimeStore(database)
    store.commit_group([], rows, None, float(rows.timestamp.max()), {})
    store.close()
    RuntimeStore(empty).close()
    refused = start_dashboard("--site", str(own_site), "--users", str(users_file),
                              "--db", str(empty))
    status, _, body = Browser(refused.url, VIEWER).get("/api/replay")
    assert status == 400 and b"empty.db" in body and str(folder).encode() not in body, body
    served = start_dashboard("--site", str(own_site), "--users", str(users_file),
                             "--db", str(database))
    viewer = Browser(served.url, VIEWER)
    answers = [viewer.get("/api/status"), viewer.get("/api/replay/info")]
    parts = urlsplit(served.url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    try:
        connection.request("GET", "/api/replay", headers=viewer.headers)
        response = connection.getresponse()
        first = response.fp.readline()
        answers.append((response.status, {}, first))
    finally:
        connection.close()
    for status, _, body in answers:
        assert status == 200, body
        assert str(folder) not in body.decode(), body
    assert b"plane1.db" in answers[0][2] and b"plane1.db" in answers[1][2]
