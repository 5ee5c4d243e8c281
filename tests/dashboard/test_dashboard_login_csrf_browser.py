"""Login cross-site request forgery, in headless Chromium against a real `cblrs dashboard`: a
page on another origin submits the login form's JSON (the JSON-in-a-text/plain-form trick)
with the attacker's own name and password, so that the victim's browser would hold the
attacker's session (what the victim then does or draws is done as the attacker)."""

from __future__ import annotations

import json

from dashboard_helpers import VIEWER
from test_dashboard_security_browser import EvilSite, evil_page


def test_another_site_cannot_log_the_browser_in(users_file, wildtrack_site, start_dashboard, page):
    url = start_dashboard("--site", str(wildtrack_site), "--users", str(users_file)).url
    evil = EvilSite(evil_page(f"{url}api/login", {"user": VIEWER[0], "password": VIEWER[1]}))
    try:
        for form in ("plain", "urlencoded"):
            page.goto(evil.url)
            with page.expect_navigation() as navigation:
                page.evaluate(f"document.getElementById('{form}').submit()")
            response = navigation.value
            assert response is not None and response.status in (400, 403), form
            if response.status == 403:
                assert "another site" in json.loads(response.text())["error"]
        assert not [
            cookie
            for cookie in page.context.cookies(url)
            if cookie["name"].endswith("cblrs_session")
        ]
    finally:
        evil.close()
