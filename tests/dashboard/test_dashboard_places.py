"""The places editor's API (in-process, through the dashboard's own middleware and roles).

A site of two planes with zones and lines on both, an alert rule on one zone: a viewer reads
the places and is refused the save; cross-site and non-JSON saves are refused; bad names and
bad geometry are refused with one sentence and the file untouched; the admin's save writes the
file (the old one kept as ``.bak``), the file reloads with exactly the new places, the places
of the other plane are kept, the running dashboard draws the new ones, and a save from a page
that read an older file is refused.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from dashboard_helpers import ADMIN, VIEWER

from cblrs.dashboard.app import DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator
from cblrs.dashboard.places_editor import MATCHER_NOTE
from cblrs.site import load_site

ORIGIN = "http://127.0.0.1"
SITE = {
    "version": 1,
    "name": "yard",
    "planes": [{"id": 1, "name": "ground", "origin": [0.0, 0.0], "size": [20.0, 10.0]},
               {"id": 2, "name": "deck", "origin": [40.0, 0.0], "size": [10.0, 10.0]}],
    "places": {
        "zones": [{"name": "gate area", "polygon": [[1, 1], [5, 1], [5, 4], [1, 4]],
                   "plane_id": 1, "hysteresis_m": 0.3},
                  {"name": "deck zone", "polygon": [[41, 1], [45, 1], [45, 5]],
                   "plane_id": 2}],
        "lines": [{"name": "door", "start": [10, 0], "end": [10, 6], "plane_id": 1,
                   "rule": "side_change"}],
    },
    "alerts": {"rules": [{"name": "crowd", "kind": "occupancy", "zone": "gate area",
                          "above": 10, "for_s": 30}]},
}


@pytest.fixture
def site_path(tmp_path) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(SITE, sort_keys=False))
    return path


@pytest.fixture
def clients(site_path, users_file, tmp_path):
    """``client(user)`` -> a logged-in TestClient of one dashboard on plane 1."""
    from starlette.testclient import TestClient

    auth = Authenticator(users_path=users_file)
    app = create_app(DashboardConfig(site_path, 1, references=tmp_path / "r"), auth)
    made = {}

    def client(user: tuple[str, str]):
        if user not in made:
            browser = TestClient(app, base_url=ORIGIN)
            answer = browser.post("/api/login", json={"user": user[0], "password": user[1]},
                                  headers={"Origin": ORIGIN})
            assert answer.status_code == 200, answer.text
            browser.headers.update({"Origin": ORIGIN,
                                    "X-CBLRS-Session": answer.json()["session"]})
            made[user] = browser
        return made[user]

    return client


def edited(view: dict) -> dict:
    """The page's edit: rename the zone, move a vertex, delete the line, add a line and a
    triangle zone."""
    zones = [dict(zone) for zone in view["zones"]]
    zones[0]["name"] = "gate square"
    zones[0]["polygon"] = [list(vertex) for vertex in zones[0]["polygon"]]
    zones[0]["polygon"][2] = [6.0, 5.0]
    zones.append({"name": "bench", "polygon": [[12.0, 2.0], [16.0, 2.0], [14.0, 5.0]]})
    lines = [{"name": "path", "start": [2.0, 8.0], "end": [18.0, 8.0]}]
    return {"zones": zones, "lines": lines, "version": view["version"]}


def test_viewer_reads_places_and_is_refused_the_save(clients, site_path):
    viewer = clients(VIEWER)
    view = viewer.get("/api/places").json()
    assert view["plane"] == 1 and view["other"] == 1  # the deck's zone is not edited here
    assert [zone["name"] for zone in view["zones"]] == ["gate area"]
    assert [line["name"] for line in view["lines"]] == ["door"]
    before = site_path.read_bytes()
    answer = viewer.post("/api/places/save", json=edited(view))
    assert answer.status_code == 403
    assert answer.json()["error"] == "bob is a viewer; this needs an admin."
    assert site_path.read_bytes() == before


def test_cross_site_and_non_json_saves_are_refused(clients, site_path):
    admin = clients(ADMIN)
    body = edited(admin.get("/api/places").json())
    before = site_path.read_bytes()
    refusals = [
        (admin.post("/api/places/save", json=body, headers={"Origin": "http://evil.example"}),
         403, "another site"),
        (admin.post("/api/places/save", json=body, headers={"X-CBLRS-Session": "x" * 43}),
         401, "X-CBLRS-Session"),
        (admin.post("/api/places/save", content=yaml.safe_dump(body),
                    headers={"Content-Type": "text/plain"}), 415, "application/json"),
    ]
    for answer, status, words in refusals:
        assert answer.status_code == status, answer.text
        assert words in answer.json()["error"]
    assert site_path.read_bytes() == before
    assert not site_path.with_name("site.yaml.bak").exists()


@pytest.mark.parametrize("change, words", [
    (lambda body: body["zones"][1].update(name="<b>bench</b>"), "may not contain '<'"),
    (lambda body: body["zones"][1].update(name=""), "must not be empty"),
    (lambda body: body["lines"][0].update(name="bench"), "two places are named 'bench'"),
    (lambda body: body["lines"][0].update(name="deck zone"),
     "two places are named 'deck zone'"),
    (lambda body: body["zones"][1].update(polygon=[[12, 2], [16, 2]]), "3 to 200 vertices"),
    (lambda body: body["zones"][1].update(polygon=[[12, 2], [16, 6], [16, 2], [12, 6]]),
     "intersects itself"),
    (lambda body: body["lines"][0].update(end=[2.0, 8.0]), "zero length"),
    (lambda body: body["lines"][0].update(end=[2.0, "x"]), "two finite numbers"),
    (lambda body: body["lines"][0].update(end=[90.0, 8.0]), "outside the site's planes"),
    (lambda body: body["zones"][1].update(colour="red"), "unknown key 'colour'"),
    (lambda body: body["zones"].pop(0), "not saved"),  # the alert rule names it
    (lambda body: body.update(version="0" * 16), "changed since this page read it"),
    # a body that lacks a list is not read as "delete every place"
    (lambda body: body.pop("lines"), "gives both lists"),
    (lambda body: body.clear(), "gives both lists"),
])
def test_bad_places_are_refused_in_one_sentence(clients, site_path, change, words):
    admin = clients(ADMIN)
    body = edited(admin.get("/api/places").json())
    if words == "not saved":  # the rule follows the renamed zone; deleting it is refused
        body["zones"][0]["name"] = "gate area"
    change(body)
    before = site_path.read_bytes()
    answer = admin.post("/api/places/save", json=body)
    assert answer.status_code == 422, answer.text
    error = answer.json()["error"]
    assert words in error and error.endswith(".") and "\n" not in error
    assert site_path.read_bytes() == before


def test_admin_save_writes_the_file_that_reloads_with_the_new_places(clients, site_path):
    admin = clients(ADMIN)
    before = site_path.read_text()
    body = edited(admin.get("/api/places").json())
    body["zones"][0]["name"] = "gate area"  # the alert rule names it
    answer = admin.post("/api/places/save", json=body)
    assert answer.status_code == 200, answer.text
    result = answer.json()
    assert result["zones"] == 2 and result["lines"] == 1 and result["note"] == MATCHER_NOTE
    assert Path(result["backup"]).read_text() == before
    saved = load_site(site_path)
    zones = {zone.name: zone for zone in saved.places.zones}
    assert set(zones) == {"gate area", "bench", "deck zone"}
    assert zones["gate area"].polygon.tolist() == [[1, 1], [5, 1], [6, 5], [1, 4]]
    assert zones["gate area"].hysteresis_m == 0.3 and zones["gate area"].plane_id == 1
    assert zones["bench"].plane_id == 1  # drawn on plane 1 of a site of two planes
    assert zones["deck zone"].plane_id == 2 and zones["deck zone"].polygon.tolist()[2] == [45, 5]
    assert [(line.name, line.start.tolist(), line.end.tolist()) for line in saved.places.lines] \
        == [("path", [2.0, 8.0], [18.0, 8.0])]
    assert saved.alerts.rules[0].zone == "gate area"
    # The running dashboard draws them at once, and the editor reads the new file.
    scene = admin.get("/api/site").json()
    assert {zone["name"] for zone in scene["zones"]} == {"gate area", "bench"}
    assert [line["name"] for line in scene["lines"]] == ["path"]
    view = admin.get("/api/places").json()
    assert view["version"] != body["version"]
    # Deleting every place of the plane keeps the other plane's.
    answer = admin.post("/api/places/save", json={
        "zones": [zone for zone in view["zones"] if zone["name"] == "gate area"], "lines": [],
        "version": view["version"]})
    assert answer.status_code == 200, answer.text
    assert load_site(site_path).places.names == ["deck zone", "gate area"]


def test_a_script_saves_with_an_admin_token(site_path, tmp_path):
    """As docs/live.md shows with curl: a bearer token, JSON, no Origin, no version."""
    from starlette.testclient import TestClient

    auth = Authenticator(run_token="t" * 32)
    app = create_app(DashboardConfig(site_path, 1, references=tmp_path / "r"), auth)
    script = TestClient(app, base_url=ORIGIN, headers={"Authorization": "Bearer " + "t" * 32})
    assert [zone["name"] for zone in script.get("/api/places").json()["zones"]] == ["gate area"]
    answer = script.post("/api/places/save", json={
        "zones": [{"name": "gate area", "polygon": [[12, 2], [16, 2], [14, 5]]}], "lines": []})
    assert answer.status_code == 200, answer.text
    assert load_site(site_path).places.zone("gate area").polygon.tolist() == [
        [12, 2], [16, 2], [14, 5]]
    assert script.post("/api/places/save", json={}).status_code == 422  # not "delete all"
    assert load_site(site_path).places.names == ["deck zone", "gate area"]
    assert script.post("/api/places/save", content="{}", headers={
        "Content-Type": "text/plain"}).status_code == 415
