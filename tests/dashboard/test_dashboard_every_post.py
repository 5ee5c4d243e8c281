"""Every state-changing route of the dashboard refuses another site's request (real `cblrs
dashboard`, an admin's session).

The routes are read from the application itself, so a route added later is attacked too:
for each one, an admin's cookie and page token sent from another origin, a form, and
``text/plain`` from the same origin (what a foreign page can send without asking first) are
refused, and so is the cookie without the page token; the site file is untouched. A guard,
not a fix: every route refused these before this test was written.
"""

from __future__ import annotations

import http.client
import json
from urllib.parse import urlsplit

from dashboard_helpers import ADMIN, site_copy
from starlette.routing import Route

from cblrs.dashboard.app import DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator

EVIL = "http://evil.example"


def call(url: str, path: str, headers: dict[str, str], body: str = "{}",
         cookie: list[str] | None = None) -> tuple[int, bytes]:
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)
    try:
        connection.request("POST", path, body=body, headers=headers)
        response = connection.getresponse()
        if cookie is not None:
            cookie.append((response.getheader("Set-Cookie") or "").split(";")[0])
        return response.status, response.read()
    finally:
        connection.close()


def test_every_post_route_refuses_another_sites_request(wildtrack_site, users_file,
                                                        start_dashboard, tmp_path):
    site_path = site_copy(wildtrack_site, tmp_path / "site" / "site.yaml")
    app = create_app(DashboardConfig(site_path, 1), Authenticator(run_token="x" * 32))
    posts = sorted(route.path for route in app.routes
                   if isinstance(route, Route) and "POST" in (route.methods or ()))
    assert {"/api/login", "/api/logout", "/api/places/save", "/api/calibrate/save"} <= set(posts)
    url = start_dashboard("--site", str(site_path), "--users", str(users_file),
                          "--references", str(tmp_path / "references")).url
    own = url.rstrip("/")
    cookie: list[str] = []
    status, body = call(url, "/api/login", {"Content-Type": "application/json", "Origin": own},
                        json.dumps({"user": ADMIN[0], "password": ADMIN[1]}), cookie)
    assert status == 200 and "=" in cookie[0], body
    token = json.loads(body)["session"]
    before = site_path.read_bytes()
    for path in posts:
        if path == "/api/login":
            continue  # its own test: test_dashboard_login_csrf_browser.py
        headers = {"Cookie": cookie[0], "X-CBLRS-Session": token}
        refused = {
            "another origin": call(url, path, {**headers, "Origin": EVIL,
                                               "Content-Type": "application/json"}),
            "a form": call(url, path, {**headers, "Origin": own,
                                       "Content-Type": "application/x-www-form-urlencoded"},
                           "a=1"),
            "text/plain": call(url, path, {**headers, "Origin": own,
                                           "Content-Type": "text/plain"}),
            "no page token": call(url, path, {"Cookie": headers["Cookie"], "Origin": own,
                                              "Content-Type": "application/json"}),
        }
        statuses = {what: status for what, (status, _) in refused.items()}
        assert statuses == {"another origin": 403, "a form": 415, "text/plain": 415,
                            "no page token": 401}, (path, refused)
    assert site_path.read_bytes() == before
    # Another site's page cannot log the browser in either (a form, or JSON from its origin).
    assert call(url, "/api/login", {"Content-Type": "application/json", "Origin": EVIL},
                json.dumps({"user": ADMIN[0], "password": ADMIN[1]}))[0] == 403
