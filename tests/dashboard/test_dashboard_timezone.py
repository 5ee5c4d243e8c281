"""The dashboard shows times in the site's time zone: /api/site carries the zone and hours,
and the page's clock text (Intl.DateTimeFormat in headless Chromium) reads the local wall
clock on both daylight-saving days, labelled with the zone; UTC without a zone."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path
from zoneinfo import ZoneInfo

import yaml

from cblrs.dashboard.scene import site_scene
from cblrs.site import parse_site

STATIC = Path(__file__).resolve().parents[2] / "src" / "cblrs" / "dashboard" / "static"
SITE = {"version": 1, "name": "station", "timezone": "Europe/Zurich",
        "opening_hours": {"mon-fri": "07:00-19:00"},
        "places": {"lines": [{"name": "gate", "start": [0, -5], "end": [0, 5]}]}}


def zurich(*parts: int) -> float:
    return datetime(*parts, tzinfo=ZoneInfo("Europe/Zurich")).timestamp()


def test_the_site_scene_carries_the_zone_and_hours():
    scene = site_scene(parse_site(yaml.safe_dump(SITE)))
    assert scene["timezone"] == "Europe/Zurich"
    assert scene["opening_hours"]["mon"] == "07:00-19:00"
    assert scene["opening_hours"]["sun"] == "closed"
    plain = {key: value for key, value in SITE.items() if key not in ("timezone",
                                                                      "opening_hours")}
    assert site_scene(parse_site(yaml.safe_dump(plain)))["timezone"] is None


def test_the_page_shows_local_times_across_both_changes(page):
    page.set_content("<!doctype html><html><body></body></html>")
    page.add_script_tag(content=(STATIC / "common.js").read_text())

    def text(seconds: float, zone: str | None, with_date: bool = False) -> str:
        return page.evaluate("([s, z, d]) => Cblrs.clockText(s, z, d)",
                             [seconds, zone, with_date])

    # 01:59:59 CET, then 03:00 CEST one second later (spring); 02:30 twice in autumn.
    spring = zurich(2026, 3, 29, 1, 59, 59)
    assert text(spring, "Europe/Zurich").startswith("01:59:59.0 ")
    assert text(spring + 1, "Europe/Zurich").startswith("03:00:00.0 ")
    first = zurich(2026, 10, 25, 2, 30)
    assert text(first, "Europe/Zurich").startswith("02:30:00.0 ")
    assert text(first + 3600, "Europe/Zurich").startswith("02:30:00.0 ")
    # The label tells the two 02:30s apart (CEST/CET or GMT+2/GMT+1, as the locale names them).
    assert text(first, "Europe/Zurich") != text(first + 3600, "Europe/Zurich")
    assert text(first, "Europe/Zurich", True).startswith("2026-10-25 02:30:00.0 ")
    assert text(first, None) == "00:30:00.00 UTC"
    assert text(12.5, "Europe/Zurich") == "t = 12.5 s"  # scene seconds are not dates
    # Open or closed by the site's hours on the local wall clock (Friday 27 March 2026).
    hours = site_scene(parse_site(yaml.safe_dump(SITE)))["opening_hours"]
    cases = {(7, 0, 0): True, (6, 59, 59): False, (18, 59, 59): True, (19, 0, 0): False}
    for (hour, minute, second), expected in cases.items():
        moment = zurich(2026, 3, 27, hour, minute, second)
        assert page.evaluate("([s, z, h]) => Cblrs.openAt(s, z, h)",
                             [moment, "Europe/Zurich", hours]) is expected
    assert page.evaluate("([s, z, h]) => Cblrs.openAt(s, z, h)",
                         [zurich(2026, 3, 29, 12), "Europe/Zurich", hours]) is False  # Sunday
    assert page.evaluate("(s) => Cblrs.openAt(s, 'UTC', null)", 0) is True
