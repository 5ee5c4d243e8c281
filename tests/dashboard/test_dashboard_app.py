"""The dashboard's server side without a browser: the site scene, the API, the replay, the
bad input a user can give (`cblrs dashboard` against a broker that refuses it, ...)."""

from __future__ import annotations

import asyncio
import json
import subprocess

import numpy as np
import pytest
from dashboard_helpers import cblrs_command

from cblrs.analytics import load_site_places
from cblrs.dashboard.app import DashboardConfig, create_app
from cblrs.dashboard.auth import Authenticator
from cblrs.dashboard.feed import Subscriber, tracks_frame
from cblrs.dashboard.replay import ReplayError, StoreReplay
from cblrs.dashboard.scene import clip_to_box, site_scene
from cblrs.datasets import load_scene
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics
from cblrs.runtime.wire import decode_tracks, encode_tracks
from cblrs.site import load_site

EPOCH = 1_700_000_000.0


@pytest.fixture(scope="module")
def stored_run(wildtrack_root, wildtrack_site, tmp_path_factory):
    """A matcher database holding WILDTRACK's ground truth as tracks, with its analytics
    counted group by group as the matcher does."""
    truth = load_scene(wildtrack_root).ground_truth
    places = load_site_places(wildtrack_site).places
    path = tmp_path_factory.mktemp("run") / "matcher.db"
    store = RuntimeStore(path)
    online = OnlineAnalytics(places)
    times = np.unique(truth.timestamp)
    for t in times:
        rows = truth[truth.timestamp == t]
        from dataclasses import replace

        rows = replace(rows, timestamp=rows.timestamp + EPOCH)
        online.update(rows, t + EPOCH)
        store.commit_group([], rows, None, t + EPOCH, {}, also=online.take_writes())
    online.flush()
    store.commit_group([], truth[:0], None, times[-1] + EPOCH, {}, also=online.take_writes())
    store.close()
    return path


def test_scene_has_places_cameras_and_fields_of_view(wildtrack_site):
    scene = site_scene(load_site(wildtrack_site))
    assert scene["plane"] == 1 and len(scene["cameras"]) == 7
    assert {zone["name"] for zone in scene["zones"]} == {"crossing", "south_path",
                                                         "north_area", "west_side"}
    x0, y0, x1, y1 = scene["bounds"]
    for camera in scene["cameras"]:
        assert camera["position"] is not None
        fov = np.array(camera["fov"])
        assert len(fov) >= 3, camera["name"]
        # Clipped to the site: what the camera sees of it, not the far ground.
        assert (fov[:, 0] >= -5.001).all() and (fov[:, 0] <= 11.001).all()
        assert (fov[:, 1] >= -11.001).all() and (fov[:, 1] <= 29.001).all()
        assert x0 <= camera["position"][0] <= x1 and y0 <= camera["position"][1] <= y1


def test_clip_to_box():
    square = [[-1.0, -1.0], [3.0, -1.0], [3.0, 3.0], [-1.0, 3.0]]
    clipped = np.array(clip_to_box(square, [0.0, 0.0, 2.0, 2.0]))
    assert clipped.min() == 0.0 and clipped.max() == 2.0 and len(clipped) == 4
    assert clip_to_box([[5.0, 5.0], [6.0, 5.0], [6.0, 6.0]], [0.0, 0.0, 1.0, 1.0]) == []


def test_tracks_frame_keeps_time_of_empty_updates():
    from cblrs.detections import Tracks

    payload = encode_tracks(Tracks.empty(), 1, sequence=3, timestamp=12.5)
    frame = tracks_frame(decode_tracks(payload))
    assert frame == {"type": "tracks", "t": 12.5, "rows": []}


def test_the_live_feed_draws_no_corrections_of_the_past():
    """A matcher that re-tracked late messages publishes the corrected past; the live view
    keeps the newest frame (the correction is counted)."""
    from types import SimpleNamespace

    from cblrs.dashboard.feed import LiveFeed
    from cblrs.detections import Tracks
    from cblrs.runtime.transport.mqtt_transport import MqttSettings

    feed = LiveFeed(MqttSettings("127.0.0.1", 1), 1, "viewer-test")  # never connected
    now = Tracks([7], [20.0], [3], [[1.0, 2.0]])
    past = Tracks([1], [10.0], [3], [[5.0, 5.0]])
    for payload in (encode_tracks(now, 1, sequence=1, timestamp=20.0),
                    encode_tracks(past, 1, sequence=2, timestamp=10.0, corrected_from=9.0)):
        feed._on_tracks(1, SimpleNamespace(payload=payload, ack=lambda: None))
    assert feed.counters["tracks"] == 1 and feed.counters["corrections"] == 1
    assert feed._state[1].last_tracks == {"type": "tracks", "t": 20.0, "plane": 1,
                                          "rows": [[3, 1.0, 2.0, None]]}


def test_subscriber_drops_old_track_frames_not_events():
    async def run() -> list[str]:
        subscriber = Subscriber(asyncio.get_running_loop(), limit=3)
        for item in ({"type": "tracks", "t": 1}, {"type": "event", "key": "a"},
                     {"type": "tracks", "t": 2}, {"type": "tracks", "t": 3}):
            subscriber.push(item)
        await asyncio.sleep(0)
        return [json.dumps(await subscriber.next()) for _ in range(3)]

    kept = asyncio.run(run())
    assert '"t": 1' not in "".join(kept) and '"event"' in kept[0]


def test_replay_plays_every_row_and_event_in_time_order(stored_run):
    replay = StoreReplay(stored_run)
    info = replay.info()
    assert info["rows"] == 4785 and info["events"] > 100

    async def collect():
        return [item async for item in replay.messages(speed=10.0, start=EPOCH + 90.0)]

    messages = asyncio.run(collect())
    assert messages[0]["type"] == "hello" and messages[1]["type"] == "counts"
    assert messages[-1]["type"] == "end"
    times = [item["t"] for item in messages if item["type"] == "tracks"]
    assert times == sorted(times) and times[0] >= EPOCH + 90.0
    # Counts before the start + events replayed = every stored crossing.
    before = messages[1]["lines"]
    after = [item for item in messages if item["type"] == "event"
             and item["kind"] == "line_crossed"]
    total = sum(row["positive"] + row["negative"] for row in before.values()) + len(after)
    with RuntimeStore(stored_run, read_only=True) as store:
        ((stored,),) = store.query("SELECT COUNT(*) FROM events WHERE kind = 'line_crossed'")
    assert total == stored
    with pytest.raises(ReplayError, match="speed must be 1 to 10"):
        asyncio.run(replay.messages(speed=50.0).__anext__())
    replay.close()


def test_replay_refuses_what_is_not_a_matcher_database(tmp_path):
    other = tmp_path / "notes.txt"
    other.write_text("hello")
    with pytest.raises(ReplayError, match="cannot replay"):
        StoreReplay(other)
    with pytest.raises(ReplayError, match="cannot replay"):
        StoreReplay(tmp_path / "missing.db")


def test_api(wildtrack_site, stored_run, tmp_path):
    from starlette.testclient import TestClient

    auth = Authenticator(run_token="test-run-token")
    client = TestClient(create_app(DashboardConfig(wildtrack_site, 1, database=stored_run,
                                                   references=tmp_path / "references"), auth),
                        base_url="http://127.0.0.1",
                        headers={"Authorization": "Bearer test-run-token"})
    assert client.get("/").status_code == 200 and "cblrs" in client.get("/").text
    assert client.get("/calibrate").status_code == 200
    assert client.get("/static/dashboard.js").status_code == 200
    site = client.get("/api/site").json()
    assert site["replay"] is True and site["live"] is False and len(site["lines"]) == 3
    # The rule that made the counts goes beside them.
    assert {line["rule"] for line in site["lines"]} == {
        "past 0.5 m each side, through the segment"}
    assert client.get("/api/stream").status_code == 404
    assert client.get("/map").status_code == 404  # the site has no map image
    assert client.get("/api/replay/info").json()["rows"] == 4785
    bad = client.get("/api/replay?speed=fast")
    assert bad.status_code == 400 and "numbers" in bad.json()["error"]
    bad = client.get("/api/replay?speed=20")
    assert bad.status_code == 400 and "speed must be 1 to 10" in bad.json()["error"]
    cameras = client.get("/api/calibrate/cameras").json()["cameras"]
    assert [camera["name"] for camera in cameras][:2] == ["CVLab1", "CVLab2"]
    missing = client.get("/api/calibrate/frame/CVLab1")
    assert missing.status_code == 404 and "no frame" in missing.json()["error"]
    few = client.post("/api/calibrate/fit", json={
        "camera": "CVLab1", "image_size": [1920, 1080],
        "points": [{"u": 1, "v": 2, "x": 0, "y": 0}] * 3})
    assert few.status_code == 422 and "4" in few.json()["error"]
    unknown = client.post("/api/calibrate/fit", json={
        "camera": "nope", "image_size": [1920, 1080], "points": []})
    assert unknown.status_code == 422 and "no camera 'nope'" in unknown.json()["error"]
    garbage = client.post("/api/calibrate/fit", json={
        "camera": "CVLab1", "image_size": [1920, 1080], "points": [{"u": "x"}]})
    assert garbage.status_code == 422 and "numbers" in garbage.json()["error"]
    reference = client.get("/api/calibrate/reference/CVLab1")
    assert reference.status_code == 404 and "save first" in reference.json()["error"]


@pytest.mark.mqtt
def test_dashboard_refused_by_the_broker_says_so(wildtrack_site, start_broker, tmp_path):
    broker = start_broker(cameras=["CVLab1"], matchers=["matcher1"])
    wrong = tmp_path / "wrong.password"
    wrong.write_text("not-the-password\n")
    wrong.chmod(0o600)  # private, as a password file should be (else a warning line first)
    cases = [
        (["--username", "viewer", "--password-file", str(wrong)], "not authorized"),
        ([], "not authorized"),  # anonymous
    ]
    for extra, reason in cases:
        result = subprocess.run(
            cblrs_command("dashboard", "--site", str(wildtrack_site), "--broker",
                          broker.address, "--port", "0", *extra),
            capture_output=True, text=True, timeout=60)
        assert result.returncode != 0
        assert "Traceback" not in result.stderr
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(lines) == 1, result.stderr
        assert "did not accept the dashboard" in lines[0] and reason in lines[0].lower()


def test_dashboard_bad_arguments_say_so(wildtrack_site, tmp_path):
    from cblrs.runtime.broker.mosquitto_config import free_port

    cases = [
        (["--site", str(tmp_path / "missing.yaml")], "does not exist"),
        (["--site", str(wildtrack_site), "--db", str(tmp_path / "missing.db")],
         "cannot replay"),
        (["--site", str(wildtrack_site), "--plane", "7"], "not a plane"),
        (["--site", str(wildtrack_site), "--broker", f"127.0.0.1:{free_port()}"],
         "did not accept the dashboard"),  # nothing listens there
    ]
    for arguments, expected in cases:
        result = subprocess.run(cblrs_command("dashboard", "--port", "0", *arguments),
                                capture_output=True, text=True, timeout=60)
        assert result.returncode != 0, arguments
        assert "Traceback" not in result.stderr
        assert expected in result.stderr, (arguments, result.stderr)
