"""The places editor in a real browser (headless Chromium), and the heatmap layer.

An admin logs in through the login form, opens the editor, draws a counting line (two clicks)
and drags it, draws a zone (clicks and a double-click), names them in the text box, drags a
vertex of a zone of the file, adds a vertex to it, picks the file's line and deletes it, and
saves: a hostile name is refused with the server's sentence shown as text, then the save goes
through and the site file holds exactly what was drawn (within a screen pixel) and the map's
tables list the new places. A viewer's page has no editor, and its heatmap layer colours the
map where tracks were.
"""

from __future__ import annotations

import pytest
import yaml
from dashboard_helpers import ADMIN, VIEWER, login, wait_until

from cblrs.site import load_site

SITE = {
    "version": 1,
    "name": "yard",
    "planes": [{"id": 1, "name": "ground", "origin": [0.0, 0.0], "size": [20.0, 10.0]}],
    "places": {
        "zones": [{"name": "gate area", "polygon": [[1, 1], [5, 1], [5, 4], [1, 4]]}],
        "lines": [{"name": "door", "start": [10, 1], "end": [10, 6]}],
    },
}


@pytest.fixture
def site_path(tmp_path):
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(SITE, sort_keys=False))
    return path


def metres_per_pixel(page) -> float:
    (ax, _), (bx, _) = (page.evaluate(f"window.cblrsPlaces.worldToScreen({x}, 0)")
                        for x in (0, 10))
    return 10.0 / (bx - ax)


def test_admin_draws_renames_moves_deletes_and_saves(site_path, start_dashboard, users_file,
                                                     page, tmp_path):
    url = start_dashboard("--site", str(site_path), "--users", str(users_file),
                          "--references", str(tmp_path / "references")).url
    login(page, url, ADMIN)
    wait_until(lambda: page.evaluate("window.cblrsPlaces !== undefined"), 20, "the map")
    assert page.is_visible("#edit-places") and not page.is_visible("#places-editor")
    page.click("#edit-places")
    wait_until(lambda: page.evaluate("window.cblrsPlaces.editing()"), 10, "the editor")
    assert page.is_visible("#places-editor")
    tolerance = 1.5 * metres_per_pixel(page)

    def at(x: float, y: float) -> tuple[float, float]:
        return tuple(page.evaluate(f"window.cblrsPlaces.worldToScreen({x}, {y})"))

    # A line: two clicks, then its name.
    page.click("#draw-line")
    page.mouse.click(*at(2, 8))
    page.mouse.click(*at(18, 8))
    page.fill("#place-name", "north path")
    # Drag it by its middle one metre south.
    page.mouse.move(*at(10, 8))
    page.mouse.down()
    page.mouse.move(*at(10, 7), steps=5)
    page.mouse.up()
    # A zone: clicks, a double-click closes it.
    page.click("#draw-zone")
    page.mouse.click(*at(12, 2))
    page.mouse.click(*at(16, 2))
    page.mouse.dblclick(*at(14, 5))
    page.fill("#place-name", "<b>bench</b>")
    # Drag a vertex of the file's zone; pick the file's line and delete it.
    page.mouse.move(*at(5, 4))
    page.mouse.down()
    page.mouse.move(*at(6, 5), steps=5)
    page.mouse.up()
    # A vertex added on the zone's top edge, another added and removed again (shift-click).
    page.mouse.dblclick(*at(3, 4.5))
    page.mouse.dblclick(*at(1, 2.5))
    assert len(page.evaluate("window.cblrsPlaces.places()")[0]["polygon"]) == 6
    page.keyboard.down("Shift")
    page.mouse.click(*at(1, 2.5))
    page.keyboard.up("Shift")
    page.mouse.click(*at(10, 3.5))
    assert page.input_value("#place-name") == "door"
    page.click("#delete-place")
    drawn = {place["name"]: place for place in page.evaluate("window.cblrsPlaces.places()")}
    assert set(drawn) == {"gate area", "north path", "<b>bench</b>"}
    # The server refuses the markup, in one sentence shown as text; nothing is written.
    before = site_path.read_bytes()
    page.click("#save-places")
    wait_until(lambda: "not saved" in page.inner_text("#places-message"), 20, "the refusal")
    assert "may not contain '<'" in page.inner_text("#places-message")
    assert page.evaluate("document.querySelectorAll('#places-message *').length") == 0
    assert site_path.read_bytes() == before
    # Pick the zone again (click inside it), rename it, save.
    page.mouse.click(*at(14, 3))
    assert page.input_value("#place-name") == "<b>bench</b>"
    page.fill("#place-name", "bench")
    page.click("#save-places")
    wait_until(lambda: not page.evaluate("window.cblrsPlaces.editing()"), 20, "the save")
    saved = load_site(site_path).places
    assert saved.names == ["gate area", "bench", "north path"]
    expected = {"gate area": [[1, 1], [5, 1], [6, 5], [3, 4.5], [1, 4]],
                "bench": [[12, 2], [16, 2], [14, 5]]}
    for zone in saved.zones:
        got = zone.polygon.tolist()
        assert len(got) == len(expected[zone.name]), zone.name
        for point, want in zip(got, expected[zone.name], strict=True):
            assert abs(point[0] - want[0]) <= tolerance and abs(point[1] - want[1]) <= tolerance
    line = saved.line("north path")
    for point, want in ((line.start, (2, 7)), (line.end, (18, 7))):
        assert abs(point[0] - want[0]) <= tolerance and abs(point[1] - want[1]) <= tolerance
    assert site_path.with_name("site.yaml.bak").read_bytes() == before
    # The map lists the new places at once.
    wait_until(lambda: "north path" in page.inner_text("#lines"), 10, "the new line's row")
    assert "door" not in page.inner_text("#lines")
    assert "bench" in page.inner_text("#zones")
    assert "matcher" in page.inner_text("#notice")


def test_viewer_has_no_editor_and_sees_the_heatmap(site_path, start_dashboard, users_file,
                                                   page, tmp_path):
    url = start_dashboard("--site", str(site_path), "--users", str(users_file),
                          "--references", str(tmp_path / "references")).url
    login(page, url, VIEWER)
    wait_until(lambda: page.evaluate("window.cblrsPlaces !== undefined"), 20, "the map")
    assert not page.is_visible("#edit-places") and not page.is_visible("#places-editor")
    (x, y) = page.evaluate("window.cblrsPlaces.worldToScreen(15, 7)")
    page.mouse.click(x, y)
    page.keyboard.press("Delete")
    assert not page.evaluate("window.cblrsPlaces.editing()")
    # Tracks standing at (15, 7): the heatmap colours that spot once it is switched on.
    pixel = ("(() => { const c = document.getElementById('map');"
             " const r = c.getBoundingClientRect();"
             " const k = window.devicePixelRatio || 1; return Array.from(c.getContext('2d')"
             f".getImageData(Math.round(({x} - r.left) * k), Math.round(({y} - r.top) * k), 1, 1)"
             ".data); })()")
    page.evaluate("for (let i = 0; i < 50; i++) "
                  "window.cblrsPlaces.addHeat([[1, 15, 7], [2, 3, 8]])")
    assert page.evaluate("window.cblrsPlaces.heat().added") == 100
    before = page.evaluate(pixel)
    assert before[0] < 100  # the dark map
    page.check("#heatmap")
    wait_until(lambda: page.evaluate(pixel)[0] > 150, 10, "the heatmap drawn at (15, 7)")
    page.uncheck("#heatmap")
    wait_until(lambda: page.evaluate(pixel)[0] < 100, 10, "the heatmap hidden")
