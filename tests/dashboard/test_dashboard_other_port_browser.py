"""A server on another port of the dashboard's host gets the admin's session cookie, and the
cookie alone is worth nothing there (real `cblrs dashboard`, real Mosquitto, real Chromium).

Browsers keep cookies by host, not by port: a page of 127.0.0.1:9999 (another local user's
process, say) that the admin opens receives the dashboard's session cookie with its request,
as does a form or fetch it makes to the dashboard (``SameSite`` ignores ports). The other
server can then replay the cookie from its own code, with any ``Origin`` it likes. The
dashboard must refuse it everything: the session's secret (``/api/session``), the live
stream, a save, and data; a browser session needs the page token that the login gave the
dashboard's own page, which lives in that origin's ``sessionStorage`` (scheme, host and
port) where no other port's page can read it. A new tab gets the token from an open tab of
the dashboard, else goes to the login page.
"""

from __future__ import annotations

import http.client
import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlsplit

from dashboard_helpers import ADMIN, login, site_copy, wait_until


class CookieCatcher:
    """Another port of 127.0.0.1: serves a page that tries to read the dashboard's token,
    and keeps the Cookie headers the browser sends it."""

    PAGE = b"""<!doctype html><html><body><script>
window.stolen = {storage: JSON.stringify(sessionStorage), local: JSON.stringify(localStorage),
                 cookie: document.cookie};
</script></body></html>"""

    def __init__(self) -> None:
        self.cookies: list[str] = []
        catcher = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                catcher.cookies.append(self.headers.get("Cookie", ""))
                self.send_response(200)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(catcher.PAGE)))
                self.end_headers()
                self.wfile.write(catcher.PAGE)

            def log_message(self, *args) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def replay(url: str, path: str, cookie: str, method: str = "GET", body: str | None = None,
           csrf: str | None = None) -> tuple[int, bytes]:
    """The other server's request to the dashboard with the caught cookie, dressed as the
    dashboard's own page (Origin, Referer: a server may send any), with the CSRF token if
    the dashboard gave it one."""
    parts = urlsplit(url)
    own = url.rstrip("/")
    headers = {"Cookie": cookie, "Origin": own, "Referer": f"{own}/",
               "Content-Type": "application/json"}
    if csrf:
        headers["X-CSRF-Token"] = csrf
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    try:
        connection.request(method, path, body=body, headers=headers)
        response = connection.getresponse()
        # a stream let through would never end: read its first bytes only
        data = response.read(200) if response.status == 200 else response.read()
        return response.status, data
    finally:
        connection.close()


def test_a_cookie_caught_on_another_port_is_refused_everything(
        wildtrack_site, users_file, start_broker, start_dashboard, page, tmp_path):
    broker = start_broker(cameras=["CVLab1"], matchers=["matcher1"])
    site_path = site_copy(wildtrack_site, tmp_path / "site" / "site.yaml")
    url = start_dashboard(
        "--site", str(site_path), "--users", str(users_file), "--broker", broker.address,
        "--username", "viewer", "--password-file", str(broker.password_file("viewer")),
        "--references", str(tmp_path / "references")).url
    catcher = CookieCatcher()
    try:
        login(page, url, ADMIN)
        wait_until(lambda: page.evaluate("window.cblrsStats && window.cblrsStats.draws > 0"),
                   60, "the dashboard page")
        own_token = str(page.evaluate("sessionStorage.getItem('cblrs-session')"))

        page.goto(catcher.url)
        wait_until(lambda: page.evaluate("window.stolen !== undefined"), 30, "the other page")
        stolen = page.evaluate("window.stolen")
        # The other port's page reads nothing of the dashboard's (another origin's storage).
        assert own_token not in json.dumps(stolen), stolen
        caught = [cookie for cookie in catcher.cookies if "cblrs_session=" in cookie]
        assert caught, catcher.cookies  # the browser did send the admin's cookie there
        cookie = caught[0]

        places = site_path.read_bytes()
        save = json.dumps({"zones": [], "lines": []})
        session = replay(url, "/api/session", cookie)
        csrf = json.loads(session[1]).get("csrf") if session[0] == 200 else None
        answers = {
            "the session": session,
            "the live stream": replay(url, "/api/stream", cookie),
            "a save": replay(url, "/api/places/save?plane=1", cookie, "POST", save, csrf),
            "the site": replay(url, "/api/site", cookie),
            "the status": replay(url, "/api/status", cookie),
            "the calibration data": replay(url, "/api/calibrate/cameras", cookie),
            "the map image": replay(url, "/map", cookie),
        }
        refused = {what: status for what, (status, _) in answers.items()}
        assert all(status in (401, 403) for status in refused.values()), answers
        assert b"csrf" not in answers["the session"][1] and own_token.encode() not in b"".join(
            body for _, body in answers.values())
        assert site_path.read_bytes() == places
        assert len(own_token) >= 32  # the page holds its token (its origin's storage only)

        # The control: the admin's own page, back in its tab, still works with its token.
        page.goto(url)
        wait_until(lambda: page.evaluate("window.cblrsStats && window.cblrsStats.draws > 0"),
                   60, "the dashboard page again")
        who = page.evaluate("Cblrs.fetchJSON('/api/session').then((s) => s.user + ' ' + s.role)")
        assert who == f"{ADMIN[0]} admin"

        # A new tab gets the token from the open dashboard tab (this origin's channel) ...
        second = page.context.new_page()
        second.goto(url)
        wait_until(lambda: second.evaluate("window.cblrsStats && window.cblrsStats.draws > 0"),
                   60, "the second tab's dashboard page")
        assert second.url == url
        assert second.evaluate("sessionStorage.getItem('cblrs-session')") == own_token
        # ... and with no dashboard tab open, a new tab goes to the login page.
        page.goto("about:blank")
        second.goto("about:blank")
        third = page.context.new_page()
        third.goto(url)
        third.wait_for_url(lambda address: "/login?next=" in address, timeout=60_000)
    finally:
        catcher.close()
