"""The login page's ``next`` cannot send a freshly logged-in browser to another site.

A link to the real dashboard's login page with ``next=/<TAB>/evil.example`` passed a check
that only looked at the first two characters; browsers drop tabs and newlines from a URL, so
the page then went to ``//evil.example``: a phishing page right after a genuine login. Here a
real Chromium logs in through such links while a second local server plays the other site.
"""

from __future__ import annotations

import secrets
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import ClassVar
from urllib.parse import quote

import pytest
from dashboard_helpers import VIEWER, login, open_login_link

from cblrs.dashboard.app import DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator


class Elsewhere(BaseHTTPRequestHandler):
    visits: ClassVar[list[str]] = []

    def do_GET(self) -> None:
        Elsewhere.visits.append(self.path)
        body = b"<title>another site</title>phished"
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *arguments) -> None:
        pass


@pytest.fixture
def elsewhere():
    server = ThreadingHTTPServer(("127.0.0.1", 0), Elsewhere)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    thread.join(5)


def test_next_never_leaves_the_dashboard(wildtrack_site, users_file, serve_app, page,
                                         elsewhere):
    url = serve_app(create_app(DashboardConfig(wildtrack_site, 1),
                               Authenticator(users_file, loopback=True)))
    targets = [f"/\t/{elsewhere}/tab", f"/\r\n\\{elsewhere}/crlf-backslash",
               f"/.//{elsewhere}/dot-segment"]
    for target in targets:
        Elsewhere.visits.clear()
        login(page, url, VIEWER, f"login?next={quote(target, safe='')}")
        page.wait_for_load_state()
        assert page.url.startswith(url), (target, page.url)
        assert Elsewhere.visits == [], (target, Elsewhere.visits)
        # leave the dashboard before logging out: its page, finding its session gone, would
        # go to /login?next=/ itself and race the next link's navigation
        page.goto("about:blank")
        page.context.clear_cookies()
    # the control: a path of the dashboard is followed
    login(page, url, VIEWER, f"login?next={quote('/?plane=1', safe='')}")
    assert page.url == f"{url}?plane=1"


def test_the_run_links_next_is_a_path_of_the_dashboard(wildtrack_site, serve_app, page,
                                                       elsewhere):
    """The run's login link logs in from its page's script (which keeps the page token) and
    follows ``next`` by the same rule as the form; its token leaves the address bar."""
    token = secrets.token_urlsafe(16)
    url = serve_app(create_app(DashboardConfig(wildtrack_site, 1),
                               Authenticator(run_token=token, loopback=True)))
    for target in (f"/\t/{elsewhere}/tab", f"//{elsewhere}/slashes",
                   f"/.//{elsewhere}/dot-segment"):
        Elsewhere.visits.clear()
        open_login_link(page, f"{url}login?token={token}&next={quote(target, safe='')}")
        page.wait_for_load_state()
        assert page.url.startswith(url), (target, page.url)
        assert Elsewhere.visits == [], (target, Elsewhere.visits)
        page.goto("about:blank")
    open_login_link(page, f"{url}login?token={token}&next={quote('/?plane=1', safe='')}")
    assert page.url == f"{url}?plane=1"
    assert page.evaluate("sessionStorage.getItem('cblrs-session')")  # the page token, kept
    # A wrong link: refused, told on the page, and the token out of the address bar.
    page.goto(f"{url}login?token=not-{token}")
    # (Not wait_for_function: polling a string is eval, which the page's CSP refuses.)
    page.wait_for_selector("#login-message:not(:empty)")
    assert "not valid" in page.inner_text("#login-message")
    assert "token" not in page.url
