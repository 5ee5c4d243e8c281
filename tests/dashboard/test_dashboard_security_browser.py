"""The dashboard's pages attacked in a real browser (headless Chromium through Playwright).

* Script in names: zone, line, site, camera and calibration-point names, and place names
  arriving from the broker (an event, the live summary, an alert), carry markup that would
  run if the page wrote them as HTML. The site-file route is closed by validation (tested in
  test_dashboard_security.py); here the validation is switched off in this process, so that
  the hostile names reach the page over the wire, as from a site file of an older cblrs or
  from a compromised matcher. None may run (no dialog, the title and a global untouched,
  no element made from them, no inline script even attempted); each must show as text.
* Cross-site requests: a page served from another origin (a second local server on another
  port of the same host, so the browser does send the session cookie) tries the save as a
  ``text/plain`` fetch, a JSON fetch, a ``text/plain`` form (the JSON-in-a-form trick) and a
  plain form, while an admin is logged in. All are refused and the site file is unchanged;
  then the admin's own page saves (the control: the session was good all along).
* A viewer's page cannot save.
"""

from __future__ import annotations

import html
import json
import secrets
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from dashboard_helpers import (
    ADMIN,
    VIEWER,
    calibration_points,
    login,
    open_login_link,
    site_copy,
    wait_until,
)

from cblrs.dashboard.app import DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator
from cblrs.dashboard.feed import LiveFeed
from cblrs.runtime.outputs.events import encode_alert, encode_event, encode_live
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import alerts_topic, events_topic, live_topic
from cblrs.site import load_site


def payload(where: str) -> str:
    """Markup that, written as HTML, runs: sets a global, the title, and opens a dialog."""
    return (f'<img src=x onerror="window.pwned=\'{where}\';document.title=\'PWNED-{where}\';'
            f'alert(\'{where}\')">')


CAMERA = "<b>CAM<b>"  # camera names may hold no space or '/' (MQTT): markup, not script


def page_state(page) -> dict:
    return page.evaluate("""({
        title: document.title,
        pwned: window.pwned === undefined ? null : String(window.pwned),
        polluted: ({}).positive !== undefined,
    })""")


@pytest.mark.mqtt
def test_hostile_names_reach_the_page_as_text(wildtrack_site, tmp_path, monkeypatch,
                                              start_broker, serve_app, page):
    # What the site file's validation would refuse, the page must still show as text.
    monkeypatch.setattr("cblrs.site.schema.check_name", lambda name, what: name)
    monkeypatch.setattr("cblrs.places.name_problem", lambda name: None)
    points = calibration_points(wildtrack_site, "CVLab2")["points"]
    for point in points:
        point["name"] = payload("POINT")

    def hostile(document: dict) -> None:
        document["name"] = payload("SITE")
        document["places"]["zones"][0]["name"] = payload("ZONE")
        document["places"]["lines"][0]["name"] = payload("LINE")
        document["cameras"][0]["name"] = CAMERA
        document["cameras"][1] = {"name": "CVLab2", "image_size": [1920, 1080],
                                  "points": [{key: point[key] for key in ("name", "u", "v",
                                                                          "x", "y")}
                                             for point in points]}

    site_path = site_copy(wildtrack_site, tmp_path / "site" / "hostile.yaml", hostile)
    assert load_site(site_path).name == payload("SITE")  # the validation is off here

    broker = start_broker(cameras=["CVLab1"], matchers=["matcher1"])
    feed = LiveFeed(broker.settings("viewer"), 1, "xss-dashboard")
    feed.start()
    publisher = MqttTransport("matcher1", broker.settings("matcher1"), persistent=False)
    publisher.connect()
    try:
        token = secrets.token_urlsafe(16)
        url = serve_app(create_app(DashboardConfig(site_path, 1, feed=feed,
                                                   references=tmp_path / "references"),
                                   Authenticator(run_token=token)))
        dialogs: list[str] = []
        console: list[str] = []
        page.on("dialog", lambda dialog: (dialogs.append(dialog.message), dialog.dismiss()))
        page.on("console", lambda message: console.append(message.text))
        open_login_link(page, f"{url}login?token={token}")
        wait_until(lambda: page.evaluate("window.cblrsStats && window.cblrsStats.connected"),
                   30, "the page's live stream")

        now = time.time()
        event = encode_event({"kind": "zone_entered", "timestamp": now, "track": 7,
                              "place": payload("EVENT"), "total": 1, "key": "xss-1",
                              "class": payload("CLASS")[:32], "crossed": True}, 1, 1)
        live = encode_live({
            "plane": 1, "sent_at": now, "clock": now,
            "cameras": [{"camera": "CVLab1", "online": True, "received": 3, "rejected": 0,
                         "rate_hz": 1.0}],
            "lines": [{"line": payload("WIRE-LINE"), "positive": 2, "negative": 1},
                      {"line": "__proto__", "positive": 5, "negative": 0}],
            "zones": [{"zone": payload("WIRE-ZONE"), "occupancy": 1, "entries": 1, "exits": 0,
                       "visits": 0, "mean_dwell_s": 0.0, "dwell": [[7, 1.5]]}],
        })

        episode = f"{payload('RULE')}/{payload('SUBJECT')}/1"
        alert = encode_alert({"episode": episode, "rule": payload("RULE"), "kind": "occupancy",
                              "subject": payload("SUBJECT"), "state": "fired",
                              "timestamp": now, "since": now - 5, "value": 12,
                              "threshold": 10},
                             1, [{"episode": episode, "rule": payload("RULE"),
                                  "kind": "occupancy", "subject": payload("SUBJECT"),
                                  "since": now - 5, "value": 12}])

        def arrived() -> bool:
            text = page.evaluate("document.querySelector('aside').textContent")
            if payload("EVENT") in text and payload("WIRE-ZONE") in text and payload(
                    "SUBJECT") in text:
                return True
            publisher.publish(events_topic(1), event)
            publisher.publish(live_topic(1), live, qos=0)
            publisher.publish(alerts_topic(1), alert)
            return False

        wait_until(arrived, 60, "the broker's hostile names on the page")
        tables = page.evaluate("""({
            lines: document.querySelector('#lines').textContent,
            zones: document.querySelector('#zones').textContent,
            cameras: document.querySelector('#cameras').textContent,
            events: document.querySelector('#events').textContent,
            alerts: document.querySelector('#alerts').textContent,
            active: document.querySelector('#alerts-active').textContent,
            header: document.querySelector('header').textContent,
            elements: document.querySelectorAll('body img, body svg, aside b, header b').length,
        })""")
        for where, text in (("ZONE", tables["zones"]), ("WIRE-ZONE", tables["zones"]),
                            ("LINE", tables["lines"]), ("WIRE-LINE", tables["lines"]),
                            ("EVENT", tables["events"]), ("SITE", tables["header"]),
                            ("RULE", tables["alerts"]), ("SUBJECT", tables["alerts"]),
                            ("RULE", tables["active"]), ("SUBJECT", tables["active"])):
            assert payload(where) in text, (where, text)
        assert CAMERA in tables["cameras"] and tables["elements"] == 0, tables
        assert "__proto__" in tables["lines"]
        state = page_state(page)
        assert state["pwned"] is None and not state["polluted"], state
        assert not state["title"].startswith("PWNED") and payload("SITE") in state["title"]

        # The calibration page: the points' names and the camera names.
        page.goto(f"{url}calibrate?camera=CVLab2")
        wait_until(lambda: page.evaluate("window.cblrsCalibrate && window.cblrsCalibrate.ready"
                                         " && window.cblrsCalibrate.fits > 0"), 60,
                   "the calibration page and its first fit")
        calibrate = page.evaluate("""({
            pairs: document.querySelector('#pairs').textContent,
            options: [...document.querySelectorAll('#camera option')].map((o) => o.textContent),
            values: [...document.querySelectorAll('#camera option')].map((o) => o.value),
            elements: document.querySelectorAll('#pairs img, #summary img, #camera b').length,
        })""")
        assert calibrate["pairs"].count(payload("POINT")) == len(points), calibrate
        assert calibrate["options"][0] == CAMERA and calibrate["values"][0] == CAMERA
        assert calibrate["elements"] == 0
        state = page_state(page)
        assert state["pwned"] is None and not state["title"].startswith("PWNED"), state
        assert dialogs == []
        # Not even blocked by the policy: nothing was ever made into script.
        assert not [line for line in console if "Content Security Policy" in line], console
    finally:
        publisher.close()
        feed.close()


class EvilSite:
    """Another origin on this machine (a second port of 127.0.0.1) serving one page."""

    def __init__(self, page_html: str):
        body = page_html.encode()

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def evil_page(save_url: str, body: dict) -> str:
    text = json.dumps(body)
    # The JSON-in-a-text/plain-form trick: name + "=" + value is the JSON document.
    name, value = text[:-1] + ', "pad": "', '"}'
    return f"""<!doctype html><html><body>
<form id="plain" method="POST" action="{save_url}" enctype="text/plain">
  <input name="{html.escape(name)}" value="{html.escape(value)}"></form>
<form id="urlencoded" method="POST" action="{save_url}">
  <input name="camera" value="CVLab1"></form>
<script>
window.results = {{}};
if (location.hash === "#fetch") (async () => {{
  const body = {json.dumps(text)};
  try {{
    const answer = await fetch("{save_url}", {{method: "POST", mode: "no-cors",
      credentials: "include", headers: {{"Content-Type": "text/plain"}}, body}});
    window.results.plain = "sent: " + answer.type;
  }} catch (error) {{ window.results.plain = "failed: " + error; }}
  try {{
    const answer = await fetch("{save_url}", {{method: "POST", credentials: "include",
      headers: {{"Content-Type": "application/json"}}, body}});
    window.results.json = "status " + answer.status;
  }} catch (error) {{ window.results.json = "blocked: " + error.name; }}
  window.results.done = true;
}})();
</script></body></html>"""


def test_cross_site_pages_cannot_save(wildtrack_site, users_file, start_dashboard, page,
                                      tmp_path):
    site_path = site_copy(wildtrack_site, tmp_path / "site" / "site.yaml")
    references = tmp_path / "references"
    served = start_dashboard("--site", str(site_path), "--users", str(users_file),
                             "--references", str(references))
    url = served.url
    save_url = f"{url}api/calibrate/save"
    body = calibration_points(site_path)
    evil = EvilSite(evil_page(save_url, body))
    answers: list[tuple[str, int]] = []
    failed: list[str] = []
    page.on("requestfailed", lambda request: failed.append(f"{request.method} {request.url} "
                                                           f"{request.failure}"))
    page.on("response", lambda response: answers.append((response.request.method,
                                                         response.status))
            if response.url == save_url else None)
    try:
        login(page, url, ADMIN)
        before = site_path.read_bytes()

        page.goto(evil.url + "#fetch")
        wait_until(lambda: page.evaluate("window.results && window.results.done"), 30,
                   "the other origin's fetches")
        results = page.evaluate("window.results")
        assert results["json"].startswith("blocked"), results  # the CORS preflight fails
        # Sent (a "simple" request needs no preflight) and answered, but the answer is
        # withheld from the other origin (Cross-Origin-Resource-Policy: same-origin).
        assert results["plain"] == "failed: TypeError: Failed to fetch", results
        assert any(line.startswith(f"POST {save_url} net::ERR_BLOCKED_BY_RESPONSE")
                   for line in failed), failed
        for form in ("plain", "urlencoded"):
            page.goto(evil.url)
            with page.expect_navigation() as navigation:
                page.evaluate(f"document.getElementById('{form}').submit()")
            response = navigation.value
            assert response is not None and response.status == 403, form
            assert "another site" in json.loads(response.text())["error"]
        assert answers == [("POST", 403), ("POST", 403)], answers  # the two forms
        assert site_path.read_bytes() == before
        assert not (references / "CVLab1.png").exists()

        # The control: the admin's own page, same session, saves.
        page.goto(url)
        wait_until(lambda: page.evaluate("window.cblrsStats && window.cblrsStats.draws > 0"), 30,
                   "the dashboard page")
        saved = page.evaluate("""(body) => Cblrs.fetchJSON('/api/calibrate/save',
            {method: 'POST', body: JSON.stringify(body)}).then((r) => r.site, (e) => e.message)""",
                              body)
        assert saved == str(site_path), saved
        assert site_path.read_bytes() != before and (references / "CVLab1.png").is_file()
        assert answers[-1] == ("POST", 200)
    finally:
        evil.close()
    # The server's own account: the fetch and both forms refused as cross-site, the JSON
    # fetch never sent (its preflight was not answered with permission), one save.
    served.process.terminate()
    _, log = served.process.communicate(timeout=30)
    refusals = [line for line in log.splitlines() if "refused POST /api/calibrate/save" in line
                and f"{evil.url[:-1]} (another site)" in line]
    assert len(refusals) == 3, log
    assert "saved the calibration of CVLab1" in log


def test_a_viewer_page_cannot_save(wildtrack_site, users_file, start_dashboard, page,
                                   tmp_path):
    site_path = site_copy(wildtrack_site, tmp_path / "site" / "site.yaml")
    url = start_dashboard("--site", str(site_path), "--users", str(users_file)).url
    login(page, url, VIEWER)
    wait_until(lambda: page.evaluate("window.cblrsStats && window.cblrsStats.draws > 0"), 30,
               "the dashboard page")
    assert page.evaluate("document.getElementById('calibrate-link').classList"
                         ".contains('hidden')")
    before = site_path.read_bytes()
    refused = page.evaluate("""(body) => Cblrs.fetchJSON('/api/calibrate/save',
        {method: 'POST', body: JSON.stringify(body)}).then(() => 'saved', (e) => e.message)""",
                            calibration_points(site_path))
    assert "needs an admin" in refused
    assert site_path.read_bytes() == before
    # The calibration page's data is an admin's: its shell loads and says so.
    page.goto(f"{url}calibrate")
    wait_until(lambda: "needs an admin" in page.inner_text("#summary"), 30,
               "the calibration page's refusal")
    assert page.evaluate("document.querySelectorAll('#camera option').length") == 0
    # Logging out ends the session: the map sends the browser to the login page.
    page.goto(url)
    wait_until(lambda: page.evaluate("window.cblrsStats && window.cblrsStats.draws > 0"), 30,
               "the dashboard page")
    page.click("#logout")
    # (page.url is Playwright's copy: wait through Playwright, which hears the navigation)
    page.wait_for_url(lambda address: address.endswith("/login"), timeout=60_000)
    page.goto(url)
    page.wait_for_url(lambda address: "/login?next=" in address, timeout=60_000)
