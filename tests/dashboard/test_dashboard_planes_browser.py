"""The overview of a site's planes in a real browser (headless Chromium through Playwright).

Two planes of the city on a real, secured Mosquitto: the planes' matchers (their logins)
publish their track updates and status, the linker (its login) the global tracks and the
site's summary; the dashboard reads them as the viewer. The page draws both planes where the
site file puts them, lists every plane's live tracks with the global id beside the plane's
track id, sums the planes' counts, shows each plane's matcher online and links each plane's
own page, which then shows that plane's tracks with their global ids.

Names with markup — a camera and a plane of the site file (its validation switched off in
this process, as for a site file of an older cblrs), a zone in the linker's summary on the
wire — show as text: no element is made of them, nothing runs.
"""

from __future__ import annotations

import secrets
import time

import pytest
from dashboard_helpers import open_login_link, wait_until
from planes_run import city_two_planes

from cblrs.dashboard.app import DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator
from cblrs.dashboard.feed import LiveFeed
from cblrs.detections import Tracks
from cblrs.runtime.outputs.events import encode_live
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import (
    live_topic,
    matcher_status_topic,
    site_tracks_topic,
    tracks_topic,
)
from cblrs.runtime.wire import encode_status, encode_tracks
from cblrs.site import load_site

pytestmark = pytest.mark.mqtt

CAMERA = "<b>CAM<b>"  # camera names may hold no space or '/' (MQTT): markup, not script
PLANE_NAME = '<img src=x onerror="window.pwned=1;alert(1)">'
ZONE = '<img src=x onerror="window.pwned=2;alert(2)">'


def live_summary(plane: int, now: float, zone: str, occupancy: int) -> bytes:
    return encode_live({
        "plane": plane, "sent_at": now, "clock": now, "cameras": [],
        "lines": [{"line": f"line_{plane}", "positive": 2 + plane, "negative": 1}],
        "zones": [{"zone": zone, "occupancy": occupancy, "entries": 3, "exits": 1,
                   "visits": 1, "mean_dwell_s": 2.0, "dwell": []}],
    })


def test_the_overview_page_shows_every_plane_and_names_as_text(
        tmp_path, monkeypatch, start_broker, serve_app, page):
    monkeypatch.setattr("cblrs.site.schema.check_name", lambda name, what: name)
    site_path, _ = city_two_planes(tmp_path)
    text = site_path.read_text()
    site_path.write_text(text.replace("name: p1-nw", f"name: '{CAMERA}'", 1)
                         .replace("name: market", f"name: '{PLANE_NAME}'", 1))
    site = load_site(site_path)
    assert CAMERA in site.camera_names and site.planes is not None

    broker = start_broker(cameras=["p1-ne"], matchers={"m1": [1], "m2": [2]},
                          linkers=["linker"])
    feed = LiveFeed(broker.settings("viewer"), [1, 2], "overview-browser")
    feed.start()
    clients = {name: MqttTransport(name, broker.settings(name), persistent=False)
               for name in ("m1", "m2", "linker")}
    for client in clients.values():
        client.connect()
    try:
        token = secrets.token_urlsafe(16)
        config = DashboardConfig(site_path, None, overview=True, feed=feed)
        url = serve_app(create_app(config, Authenticator(run_token=token)))
        dialogs: list[str] = []
        page.on("dialog", lambda dialog: (dialogs.append(dialog.message), dialog.dismiss()))
        open_login_link(page, f"{url}login?token={token}")
        # "/" answers by its address alone: its page finds an overview and goes there
        page.wait_for_url(lambda address: address.endswith("/?plane=all"), timeout=60_000)
        wait_until(lambda: page.evaluate("window.cblrsOverview && window.cblrsOverview()"
                                         ".connected"), 60, "the overview's live stream")
        for plane in (1, 2):
            clients[f"m{plane}"].publish(matcher_status_topic(plane, f"m{plane}"),
                                         encode_status(f"m{plane}", "online", role="matcher"),
                                         retain=True)
        step = [0]

        def publish_once() -> None:
            """One capture instant: the linker's global rows, then each plane's update."""
            step[0] += 1
            t = time.time()
            # plane 1's track 3 and plane 2's track 8 are one person (global 41) in the
            # overlap; plane 2's track 9 is global 42.
            clients["linker"].publish(site_tracks_topic(), encode_tracks(
                Tracks([0, 0], [t, t], [41, 42], [[40.0, 1.0], [60.0, 2.0]]), 0,
                sequence=step[0], timestamp=t, source_plane=[1, 2],
                source_track=[3, 9]), qos=0)
            clients["linker"].publish(site_tracks_topic(), encode_tracks(
                Tracks([0], [t], [41], [[40.0, 1.0]]), 0, sequence=step[0],
                timestamp=t + 0.001, source_plane=[2], source_track=[8]), qos=0)
            clients["m1"].publish(tracks_topic(1), encode_tracks(
                Tracks([0], [t], [3], [[40.0, 1.0]]), 1, sequence=step[0], timestamp=t), qos=0)
            clients["m2"].publish(tracks_topic(2), encode_tracks(
                Tracks([0, 0], [t, t], [8, 9], [[40.1, 1.0], [60.0, 2.0]]), 2,
                sequence=step[0], timestamp=t), qos=0)
            clients["m1"].publish(live_topic(1), live_summary(1, t, "north_1", 1), qos=0)
            clients["m2"].publish(live_topic(2), live_summary(2, t, "north_2", 2), qos=0)
            clients["linker"].publish(live_topic(0), live_summary(0, t, ZONE, 3), qos=0)

        def linked() -> bool:
            state = page.evaluate("window.cblrsOverview()")
            shown = {(track["plane"], track["track"], track["global"])
                     for track in state["tracks"]}
            if {(1, 3, 41), (2, 8, 41), (2, 9, 42)} <= shown and state["site"]:
                return True
            publish_once()
            return False

        wait_until(linked, 60, "both planes' tracks with their global ids on the page")
        wait_until(lambda: page.evaluate("document.querySelector('#planes tbody')"
                                         ".textContent.includes('1/1 online')"), 30,
                   "the matchers' health")
        tables = page.evaluate("""({
            planes: [...document.querySelectorAll('#planes tbody tr')].map((row) =>
                [...row.cells].map((cell) => cell.textContent)),
            total: [...document.querySelectorAll('#site-total td')].map((cell) => cell.textContent),
            links: [...document.querySelectorAll('#plane-links a')].map((a) =>
                [a.textContent, a.getAttribute('href')]),
            tracks: document.querySelector('#tracks').textContent,
            cameras: document.querySelector('#cameras').textContent,
            siteZones: document.querySelector('#site-zones').textContent,
            elements: document.querySelectorAll('body img, aside b, header b, nav img').length,
            pwned: window.pwned === undefined ? null : String(window.pwned),
        })""")
        assert [row[0] for row in tables["planes"]] == ["west", PLANE_NAME]
        assert all(row[4] == "1/1 online" for row in tables["planes"]), tables["planes"]
        # Site-wide: the sum of the planes' live tracks, zone occupancy and crossings.
        assert tables["total"][:4] == ["site", "3", "3", str((2 + 1 + 1) + (2 + 2 + 1))]
        assert tables["links"] == [["west", "/?plane=1"], [PLANE_NAME, "/?plane=2"]]
        assert "41" in tables["tracks"] and "42" in tables["tracks"]
        assert CAMERA in tables["cameras"] and ZONE in tables["siteZones"]
        assert tables["elements"] == 0 and tables["pwned"] is None, tables
        assert dialogs == []

        # Each plane's own page: that plane's tracks, with their global ids.
        page.click("#plane-links a[href='/?plane=2']")
        page.wait_for_url(lambda address: address.endswith("/?plane=2"), timeout=60_000)

        def plane_two_shown() -> bool:
            stats = page.evaluate("window.cblrsStats")
            if stats and stats["tracksShown"] == 2:
                return True
            publish_once()
            return False

        wait_until(plane_two_shown, 60, "plane 2's page with its two tracks")
        assert page.evaluate("document.querySelector('#site-name').textContent") \
            .endswith("plane 2")
        assert not page.evaluate("document.querySelector('#overview-link').classList"
                                 ".contains('hidden')")
        assert page.evaluate("window.pwned === undefined") and dialogs == []
    finally:
        for client in clients.values():
            client.close(timeout=1)
        feed.close()
