"""``cblrs demo``'s live part: the plaza's cameras replayed through ``cblrs up`` (tracks on
the live map, stopped by --live-seconds), never without a terminal unless asked, and the site
file it writes (the scene's cameras, plane and boxes, played back and forth; the plaza's
places and the demo's alert rules: counts, and an alert that fires and clears)."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
from up_helpers import ENVIRONMENT, first_on_the_stream, first_tracks_on_the_map, up_command

from cblrs.cli.main import main
from cblrs.datasets.presets import make_scene
from cblrs.site import load_site
from cblrs.up.backbone import choose_backbone
from cblrs.up.scene_site import (
    DEMO_ALERT_RULES,
    SITES,
    demo_places_and_rules,
    ping_pong,
    write_scene_site,
)

DEMO = [sys.executable, "-m", "cblrs.cli.main", "demo"]
LIVE_CHECK_S = 45
"""How long the live site runs in the alerts test (from when every process runs)."""


@pytest.mark.parametrize(("count", "total", "expected"), [
    (3, 7, [0, 1, 2, 1, 0, 1, 2]),
    (2, 5, [0, 1, 0, 1, 0]),
    (1, 3, [0, 0, 0]),
    (4, 2, [0, 1]),
    (3, 0, []),
])
def test_ping_pong_plays_the_frames_back_and_forth(count, total, expected):
    assert ping_pong(count, total).tolist() == expected


def test_the_live_site_is_the_scenes_cameras_plane_and_people(tmp_path):
    scene = make_scene("plaza", duration_s=4)
    path = write_scene_site(scene, tmp_path / "live", replay_s=10)
    site = load_site(path)
    assert [spec.name for spec in site.model.cameras] == scene.camera_names
    assert site.planes.ids == [scene.plane.plane_id]
    fps = 1 / scene.frame_interval
    frames = round(10 * fps)
    for index, spec in enumerate(site.model.cameras):
        assert spec.source.kind == "detections" and spec.source.fps == pytest.approx(fps)
        rows = np.loadtxt(tmp_path / "live" / spec.source.path, delimiter=",", ndmin=2)
        # the people of each played frame, in the ping-pong order; the cars left out
        order = ping_pong(len(scene.frames), frames)
        expected = sum(int(np.sum(scene.detections[position][index].class_id == 0))
                       for position in order)
        assert len(rows) == expected > 0
        assert rows[:, 0].min() >= 1 and rows[:, 0].max() <= frames
        # the site's camera is the scene's: the same pixel of the same ground point
        point = np.array([[1.0, 2.0]])
        np.testing.assert_allclose(site.camera(spec.name).camera.world_to_pixel(point)[0],
                                   scene.cameras[index].world_to_pixel(point)[0], atol=1e-6)


def test_the_demos_live_site_has_the_plazas_places_and_the_demos_alert_rules(tmp_path):
    scene = make_scene("plaza", duration_s=4)
    places, rules = demo_places_and_rules(scene.name)
    assert rules == DEMO_ALERT_RULES["plaza"] and rules
    site = load_site(write_scene_site(scene, tmp_path / "live", replay_s=10, places=places,
                                      alert_rules=rules))
    # the places are the checked-in plaza site's, which the offline analytics count
    checked_in = load_site(SITES / "plaza.yaml").places
    assert site.places.names == checked_in.names and len(checked_in) == 6
    for mine, theirs in zip(site.places.zones, checked_in.zones, strict=True):
        np.testing.assert_array_equal(mine.polygon, theirs.polygon)
    for mine, theirs in zip(site.places.lines, checked_in.lines, strict=True):
        np.testing.assert_array_equal([mine.start, mine.end], [theirs.start, theirs.end])
        assert mine.hysteresis_m == theirs.hysteresis_m
    assert [rule.name for rule in site.alerts.rules] == [rule["name"] for rule in rules]
    assert not site.alerts.webhooks  # the dashboard and cblrs up show them: no receiver
    zones = {zone.name for zone in site.places.zones}
    assert all(rule.zone in zones for rule in site.alerts.rules if rule.kind == "occupancy")


def test_without_the_scenes_site_file_the_live_site_has_no_places_and_no_alerts(tmp_path):
    assert demo_places_and_rules("plaza", sites=tmp_path) == (None, ())
    scene = make_scene("plaza", duration_s=2)
    site = load_site(write_scene_site(scene, tmp_path / "live", replay_s=2))
    assert len(site.places) == 0 and not site.alerts.rules


def test_the_demos_live_site_counts_and_an_alert_fires_and_clears(tmp_path):
    """The demo's live site as ``cblrs demo`` writes it, run by ``cblrs up`` with real
    processes for 45 s: the crowd alert reaches the dashboard's live stream, and the --json
    summary has counts on the plaza's lines and zones and the alert fired and cleared."""
    try:
        choose_backbone()
    except Exception as error:
        pytest.skip(f"no broker: {error}")
    scene = make_scene("plaza")  # the demo's live scene (seed 0, 30 s)
    places, rules = demo_places_and_rules(scene.name)
    site = write_scene_site(scene, tmp_path / "live", places=places, alert_rules=rules)
    process = subprocess.Popen(up_command(site, tmp_path / "live" / "state", "--stop-after",
                                          str(LIVE_CHECK_S)),
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=ENVIRONMENT)
    try:
        line = process.stderr.readline()  # with --json, the login link is on stderr
        while line and not line.startswith("dashboard: "):
            line = process.stderr.readline()
        assert line, process.communicate()[1]
        shown = first_on_the_stream(
            line.split(" ", 1)[1].strip(),
            lambda item: item.get("type") == "alert" and item["state"] == "fired",
            LIVE_CHECK_S, "no alert on the dashboard")
        stdout, stderr = process.communicate(timeout=150)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert (shown["rule"], shown["subject"], shown["episode"]) == ("crowd", "centre",
                                                                    "crowd/centre/1"), shown
    assert process.returncode == 0, stderr
    summary = json.loads(stdout)
    plane = summary["planes"]["1"]
    counts = plane["counts"]
    assert list(counts["lines"]) == ["plaza_middle", "plaza_north", "road"], counts
    assert list(counts["zones"]) == ["centre", "west", "east"], counts
    crossings = sum(sum(row.values()) for row in counts["lines"].values())
    entries = sum(row["entries"] for row in counts["zones"].values())
    assert crossings > 0 and entries > 0, counts
    alerts = plane["alerts"]
    assert alerts["fired"] >= 1 and alerts["cleared"] >= 1, alerts
    assert alerts["undelivered"] == {"broker": 0}, alerts
    print(f"demo's live site, {LIVE_CHECK_S} s: {crossings} crossings, {entries} zone "
          f"entries, alerts {alerts['fired']} fired, {alerts['cleared']} cleared; "
          f"{summary['backbone']}")


def test_without_a_terminal_the_demo_does_not_go_live(tmp_path):
    result = subprocess.run([*DEMO, "--preset", "roundabout", "--duration", "3", "--out",
                             str(tmp_path / "demo"), "--quiet"], capture_output=True,
                            text=True, timeout=300, stdin=subprocess.DEVNULL, env=ENVIRONMENT)
    assert result.returncode == 0, result.stderr
    assert not (tmp_path / "demo" / "live").exists()
    assert "dashboard:" not in result.stdout


@pytest.mark.parametrize("extra", [["--json"], ["--no-live"], ["--dataset", "x"]])
def test_live_seconds_with_an_option_that_excludes_it_is_one_sentence(tmp_path, capsys,
                                                                      extra):
    code = main(["demo", "--out", str(tmp_path), "--live-seconds", "5", *extra])
    assert code == 2
    assert "--live-seconds goes without --no-live, --json and --dataset" in (
        capsys.readouterr().err)


def test_the_demo_goes_live_tracks_reach_the_map_and_it_stops_after_live_seconds(tmp_path):
    try:
        backbone = choose_backbone()
    except Exception as error:
        pytest.skip(f"no broker: {error}")
    out = tmp_path / "demo"
    started = time.monotonic()
    process = subprocess.Popen([*DEMO, "--preset", "roundabout", "--duration", "3", "--out",
                                str(out), "--live-seconds", "150"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=ENVIRONMENT)
    try:
        line = process.stdout.readline()
        while line and not line.startswith("dashboard: "):
            line = process.stdout.readline()
        assert line, process.communicate()[1]
        assert "/login?token=" in line
        rows = first_tracks_on_the_map(line.split(" ", 1)[1].strip(), timeout=90)
        on_the_map_s = time.monotonic() - started
        process.send_signal(2)  # Ctrl-C stops it before --live-seconds
        stdout, stderr = process.communicate(timeout=90)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert rows and all(len(row) == 4 for row in rows), rows
    assert process.returncode == 0, stderr
    assert "SIGINT: stopping cameras, matchers, dashboard, broker" in stdout
    state = json.loads((out / "live" / "state" / "up.json").read_text())
    assert state["backbone"] == backbone.kind
    assert (out / "roundabout" / "metrics.json").is_file()  # the offline part ran first
    print(f"demo: tracks on the live map {on_the_map_s:.1f} s after cblrs demo started "
          f"({backbone.kind})")


def test_live_seconds_stops_the_site_by_itself(tmp_path):
    try:
        choose_backbone()
    except Exception as error:
        pytest.skip(f"no broker: {error}")
    out = tmp_path / "demo"
    result = subprocess.run([*DEMO, "--preset", "roundabout", "--duration", "3", "--out",
                             str(out), "--live-seconds", "3", "--quiet"], capture_output=True,
                            text=True, timeout=300, env=ENVIRONMENT)
    assert result.returncode == 0, result.stderr
    assert "dashboard: http://127.0.0.1:" in result.stdout
    assert (out / "live" / "state" / "plane1.db").is_file()
