"""The pages (``/``, ``/calibrate``) tell a caught session cookie nothing, and nothing the
cookie alone asks keeps its session alive (real `cblrs dashboard`, real Chromium).

A server on another port of the dashboard's host receives the session cookie of a user
whose browser visits it (browsers send a host's cookies to every port). Every API route
refuses that cookie without the page token, but the pages took the cookie alone: their
answers told whether the session was alive (200 against a redirect), whose it was and its
role (``/calibrate``: "bob is a viewer; this needs an admin."), which planes the site has
(``/?plane=N``: 404 naming them) and whether the dashboard is an overview; and each
request counted as the session's activity, so the other server kept a session that its
user had left alive for as long as it liked, past the idle time-out. Now a page's answer
depends on nothing but the path and whether the request carries a cookie at all: a caught
cookie gets exactly what a made-up one gets, and keeps nothing alive. The API routes refused
the cookie without its page token, but still counted the request as the session's activity
(the session was looked up and touched before the token was checked): now only a request
with both is.
"""

from __future__ import annotations

import http.client
import time
from urllib.parse import urlsplit

from dashboard_helpers import VIEWER, login, site_copy, wait_until
from test_dashboard_other_port_browser import CookieCatcher

PAGES = ["/", "/calibrate", "/?plane=1", "/?plane=7", "/?plane=all", "/calibrate?camera=C1"]
IDLE_MINUTES = 0.2  # 12 s


def get(url: str, path: str, headers: dict[str, str]) -> tuple[int, str, bytes]:
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=60)
    try:
        connection.request("GET", path, headers=headers)
        response = connection.getresponse()
        return response.status, response.getheader("Location") or "", response.read()
    finally:
        connection.close()


def test_a_caught_cookie_learns_nothing_from_the_pages_and_keeps_nothing_alive(
        wildtrack_site, users_file, start_dashboard, page, tmp_path):
    site_path = site_copy(wildtrack_site, tmp_path / "site" / "site.yaml")
    url = start_dashboard("--site", str(site_path), "--users", str(users_file),
                          "--idle-minutes", str(IDLE_MINUTES)).url
    catcher = CookieCatcher()
    try:
        login(page, url, VIEWER)
        wait_until(lambda: page.evaluate("window.cblrsStats && window.cblrsStats.draws > 0"),
                   60, "the dashboard page")
        token = str(page.evaluate("sessionStorage.getItem('cblrs-session')"))
        page.goto(catcher.url)  # the viewer leaves the dashboard for the other port's page
        wait_until(lambda: page.evaluate("window.stolen !== undefined"), 30, "the other page")
        caught = [cookie for cookie in catcher.cookies if "cblrs_session=" in cookie]
        assert caught, catcher.cookies
        cookie = caught[0]
        name = cookie.split("=", 1)[0]
        own = {"Cookie": cookie, "X-CBLRS-Session": token}
        assert get(url, "/api/session", own)[0] == 200  # the session is alive now

        # What the pages answer the caught cookie is what they answer a made-up one.
        forged = f"{name}={'x' * 43}"
        for path in PAGES:
            with_caught = get(url, path, {"Cookie": cookie})
            with_forged = get(url, path, {"Cookie": forged})
            assert with_caught == with_forged, (path, with_caught[:2], with_forged[:2])
            assert VIEWER[0].encode() not in with_caught[2] and b"viewer" not in with_caught[2]

        # The other server asks for a page, and for data (refused), every 2 s, long past
        # the idle time-out: the session its user left still ends.
        deadline = time.monotonic() + IDLE_MINUTES * 60 * 2.5
        while time.monotonic() < deadline:
            assert get(url, "/", {"Cookie": cookie})[0] in (200, 303)
            assert get(url, "/api/session", {"Cookie": cookie})[0] == 401
            time.sleep(2)
        status, _, body = get(url, "/api/session", own)
        assert status == 401, body
    finally:
        catcher.close()

    # A browser with no cookie at all goes to the login page, as before.
    status, location, _ = get(url, "/calibrate", {})
    assert status == 303 and location == "/login?next=%2Fcalibrate"
