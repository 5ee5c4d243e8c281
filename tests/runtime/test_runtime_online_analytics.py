"""Online analytics end to end: a real Mosquitto, `cblrs matcher --site` killed and restarted.

Seven WILDTRACK cameras (camera nodes, each its own MQTT user) publish a 60 s stretch through
a Mosquitto with users and an ACL; the matcher (`cblrs matcher --site site.yaml`, a process)
counts the site's lines and zones as it tracks, is killed with SIGKILL a quarter of the way
in and restarted on the same database. Then:

* every message was tracked exactly once;
* the counts the matcher stored equal `cblrs analytics` (the offline command) on the tracks
  the matcher stored, and equal the analytics of an uninterrupted in-process run: the kill
  changed nothing;
* every event the matcher committed reached the read-only viewer (de-duplicated by key,
  QoS 1 may repeat one) and validates against ``cblrs.events/1``; a camera user cannot read
  them;
* the metrics endpoint of the restarted matcher answers /healthz, /readyz and /metrics.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from waiting import wait_until

from cblrs.analytics import analyse_tracks
from cblrs.cli.main import main
from cblrs.datasets import load_scene
from cblrs.datasets.aicity import write_tracks
from cblrs.matching import make_matcher
from cblrs.pipeline import track_scene
from cblrs.runtime.broker.mosquitto_config import free_port
from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.analytics_store import count_summary, read_counts, read_events, read_od
from cblrs.runtime.outputs.events import decode_event
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.protocol import TransportError, Will
from cblrs.runtime.transport.topics import events_topic, matcher_status_topic
from cblrs.runtime.wire import decode_status
from cblrs.site import load_site

pytestmark = [pytest.mark.mqtt, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
FRAMES = (0, 595)  # 120 annotated frames, 60 s of the scene
PACE_S = 0.04  # seconds between a camera's frames: the replay runs at ~12x
HOLDS = (40, 80)
"""Each camera stops after these many frames until the test lets it go on: a third of the
way in (the first matcher is killed while they wait, so the kill is mid-stream however slow
the machine), then two thirds (the restarted matcher is scraped while they wait, so it is
running); between the two they publish while no matcher runs."""
WAIT = 120.0
"""The bound of a wait for an event: it only fails the test, it never delays it."""
METRICS = (
    "cblrs_messages_received_total",
    "cblrs_capture_to_track_seconds_bucket",
    "cblrs_stage_duration_seconds_bucket",
    "cblrs_camera_last_seen",
)
MATCHER = "matcher1"


@pytest.fixture(scope="module")
def site_file(wildtrack_root, tmp_path_factory) -> Path:
    """`cblrs site init` for WILDTRACK, with the places of sites/wildtrack.yaml."""
    folder = tmp_path_factory.mktemp("site")
    path = folder / "site.yaml"
    assert main(["site", "init", str(wildtrack_root), "--out", str(path)]) == 0
    document = yaml.safe_load(path.read_text())
    document["places"] = yaml.safe_load((REPO / "sites/wildtrack.yaml").read_text())["places"]
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def case(wildtrack_root, site_file):
    site = load_site(site_file)
    scene = load_scene(wildtrack_root).select_frames(*FRAMES)
    references = [site.render_reference(name) for name in scene.camera_names]
    return {"site": site, "scene": scene, "references": references}


def paced(frames, seconds: float, holds: dict[int, threading.Event]):
    """The frames, ``seconds`` apart; after the n-th, wait for ``holds[n]`` if there is one."""
    for count, frame in enumerate(frames, 1):
        yield frame
        time.sleep(seconds)
        if count in holds:
            assert holds[count].wait(WAIT), f"the test never let the cameras past frame {count}"


def start_cameras(
    case, broker, epoch: float, holds: dict[int, threading.Event] | None = None
) -> list[threading.Thread]:
    """One camera node per camera, each logged in as its own broker user, paced.

    ``holds`` stops every camera after its n-th frame until ``holds[n]`` is set (none: no stop);
    test_runtime_alerts starts its cameras with this function too, without holds.
    """
    holds = holds or {}
    from cblrs.runtime.camera.sources import scene_source

    scene = case["scene"]
    threads = []
    for index, name in enumerate(scene.camera_names):

        def run(index=index, name=name) -> None:
            transport = MqttTransport(
                f"online-{name}",
                broker.settings(name),
                persistent=False,
                will=Will(*camera_last_will(1, name)),
            )
            transport.connect()
            node = CameraNode(
                transport, 1, name, case["references"][index], epoch=epoch, flush_timeout_s=30.0
            )
            node.run(paced(scene_source(scene, index), PACE_S, holds), connect=False)
            transport.close()

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        threads.append(thread)
    return threads


def matcher_command(site_file: Path, database: Path, broker, http_port: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "cblrs.cli.main",
        "matcher",
        "--site",
        str(site_file),
        "--db",
        str(database),
        "--broker",
        f"127.0.0.1:{broker.port}",
        "--username",
        MATCHER,
        "--password-file",
        str(broker.files.password_files[MATCHER]),
        # A restarted matcher gets its session's backlog from the broker camera by camera: on
        # a loaded machine a camera's part could come more than 5 s after another's, and a
        # 5 s window released frames without it (late, re-tracked: the events published
        # before the re-tracking were no longer the stored ones). The cameras' "offline"
        # at the end ends every wait, so the longer window costs no time.
        "--window",
        "60",
        "--until-cameras-offline",
        "--idle-exit",
        str(WAIT),
        "--http",
        f"127.0.0.1:{http_port}",
        "--json",
    ]


def offline_counts(tracks_file: Path, site_file: Path, out: Path) -> dict:
    """`cblrs analytics` on a tracks file, read back from its analytics.json."""
    code = main(
        [
            "analytics",
            str(tracks_file),
            "--site",
            str(site_file),
            "--fps",
            "10",
            "--out",
            str(out),
            "--no-plots",
            "--json",
        ]
    )
    assert code == 0
    return json.loads((out / "analytics.json").read_text())


def test_online_counts_equal_offline_and_survive_sigkill(
    case, site_file, start_mosquitto, tmp_path
):
    scene = case["scene"]
    names = scene.camera_names
    # A camera user of its own for the spy: the broker takes the user name as the client
    # id, so a spy logged in as a running camera would take over that camera's session
    # (and the two would throw each other off).
    broker = start_mosquitto(cameras=[*names, "spy"], matchers=[MATCHER], plane_ids=(1,))
    database = tmp_path / "matcher.db"
    total = len(scene.frames) * len(names)
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}

    # The read-only viewer collects the events; a camera may not read them.
    received: list[bytes] = []
    viewer = MqttTransport("online-viewer", broker.settings("viewer"), persistent=True)

    def on_event(delivery) -> None:
        received.append(bytes(delivery.payload))
        delivery.ack()

    viewer.subscribe(events_topic(1), on_event, qos=1)
    viewer.connect()
    spy = MqttTransport("online-spy", broker.settings("spy"), persistent=False)
    spied: list[bytes] = []
    spy.connect()
    try:
        spy.subscribe(events_topic(1), lambda delivery: spied.append(delivery.payload), qos=1)
    except TransportError:
        pass  # refused outright: the ACL at work
    matcher_online = threading.Event()

    def on_status(delivery) -> None:
        if decode_status(delivery.payload).state == "online":
            matcher_online.set()
        delivery.ack()

    viewer.subscribe(matcher_status_topic(1, MATCHER), on_status)
    first = subprocess.Popen(
        matcher_command(site_file, database, broker, free_port()),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=environment,
    )
    epoch = float(int(time.time()) - 600)
    holds = {count: threading.Event() for count in HOLDS}
    try:
        wait_until(matcher_online.is_set, WAIT, "the matcher to come online")
        threads = start_cameras(case, broker, epoch, holds)

        def processed() -> int:
            with RuntimeStore(database, read_only=True) as store:
                return store.counters().get("processed", 0)

        wait_until(lambda: processed() >= total // 4, WAIT, "a quarter to be processed")
        first.send_signal(signal.SIGKILL)
        first.wait(WAIT)
        killed_at = processed()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
        holds[HOLDS[0]].set()  # the cameras go on while no matcher runs
    with RuntimeStore(database, read_only=True) as store:
        events_at_kill = len(read_events(store))
    http_port = free_port()
    second = subprocess.Popen(
        matcher_command(site_file, database, broker, http_port),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=environment,
    )
    # The restarted matcher's metrics, scraped while it runs (the cameras wait meanwhile).
    scraped: dict[str, str] = {}

    def scrape(path: str) -> str:
        with urllib.request.urlopen(f"http://127.0.0.1:{http_port}{path}", timeout=5) as answer:
            return answer.read().decode()

    def scraped_all() -> bool:
        try:
            for path in ("/readyz", "/healthz", "/metrics"):
                scraped[path] = scrape(path)
        except OSError:
            return second.poll() is not None
        return all(name in scraped["/metrics"] for name in METRICS)

    try:
        wait_until(scraped_all, WAIT, "the restarted matcher's metrics")
    finally:
        holds[HOLDS[1]].set()
    out, err = second.communicate(timeout=2 * WAIT)
    for thread in threads:
        thread.join(WAIT)
    with RuntimeStore(database, read_only=True) as store:
        committed = {event.body["key"] for event in read_events(store)}
    assert committed, "no event was committed"
    wait_until(
        lambda: {decode_event(p).key for p in list(received)} >= committed,
        WAIT,
        "every committed event at the viewer",
    )
    viewer.close()
    spy.close()
    assert second.returncode == 0, err
    summary = json.loads(out)
    assert 0 < killed_at < total, "the kill was not mid-stream"
    assert 0 < events_at_kill, "no event was counted before the kill"
    # Under load a restarted matcher may release a window before every camera's queued
    # messages reached it: those are late, re-tracked, and the analytics follow.
    assert summary["processed"] == total
    assert summary["late"] == summary.get("late_tracked", 0), summary

    with RuntimeStore(database, read_only=True) as store:
        tracks = store.tracks()
        counts = count_summary(read_counts(store))
        od = read_od(store)
        stored_events = read_events(store)
        counters = store.counters()
    assert counters["processed"] == total, "a message was tracked twice or lost"
    assert counters.get("analytics_late_rows", 0) == 0
    assert counters["analytics_rows"] == len(tracks), "a row was counted twice or not at all"
    assert all(event.published for event in stored_events)

    # Online == offline `cblrs analytics` on the same tracks.
    tracks_file = tmp_path / "stored.txt"
    write_tracks(tracks_file, tracks)
    offline = offline_counts(tracks_file, site_file, tmp_path / "offline")
    crossings = 0
    for row in offline["lines"]:
        if row["class"] != "all":
            continue
        online_count = counts["lines"].get(row["line"], {}).get(row["direction"], 0)
        assert online_count == row["count"], (row, counts["lines"])
        crossings += row["count"]
    assert crossings > 10, "too few crossings to show anything"
    for row in offline["zones"]:
        zone = counts["zones"].get(row["zone"], {})
        for measure in ("entries", "appeared", "exits", "visits"):
            assert zone.get(measure, 0) == row[measure], (row["zone"], measure, zone, row)
        if row["visits"]:
            # Times differ by float rounding only: online ones carry the 1.7e9 s epoch.
            assert zone["mean_dwell_s"] == pytest.approx(row["mean_dwell_s"], abs=1e-4)
    offline_od = {
        (origin, destination): value
        for origin, row in offline["od"].items()
        for destination, value in row.items()
        if value
    }
    assert od == offline_od

    # `cblrs matcher --stats` shows the persistent counts.
    stats = subprocess.run(
        [sys.executable, "-m", "cblrs.cli.main", "matcher", "--stats", str(database)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    north = counts["lines"]["north_flow"]
    shown = re.search(
        r"line north_flow \+/-\s+(\d+) / (\d+) \(counted when: past 0\.5 m each "
        r"side, through the segment\)",
        stats,
    )
    assert shown is not None, stats
    assert (int(shown[1]), int(shown[2])) == (north.get("positive", 0), north.get("negative", 0))

    # The kill changed nothing: the same counts as an uninterrupted in-process run.
    site = case["site"]
    positions = {name: list(xyz) for name, xyz in site.camera_positions().items()}
    uninterrupted = track_scene(
        replace(scene, timestamps=epoch + scene.timestamps, plane=site.planes[0]),
        matcher=make_matcher("fusion", site.planes, names, camera_positions=positions),
        references=case["references"],
    ).tracks
    np.testing.assert_array_equal(tracks.track_id, uninterrupted.track_id)
    expected = analyse_tracks(uninterrupted, site.places)
    for row in expected.lines:
        if row["class"] == "all":
            assert counts["lines"].get(row["line"], {}).get(row["direction"], 0) == row["count"]

    keys = [decode_event(payload).key for payload in received]
    print(
        f"\nkilled at {killed_at}/{total} messages processed, {events_at_kill} events; "
        f"after the restart: {crossings} crossings, {len(stored_events)} events, "
        f"{len(received)} event deliveries to the viewer ({len(received) - len(set(keys))} "
        f"repeated), lines {counts['lines']}"
    )

    # Every committed event reached the viewer, once per key; none reached the camera user.
    assert set(keys) == {event.body["key"] for event in stored_events}
    assert len(stored_events) == (
        crossings
        + sum(row["entries"] + row["appeared"] + row["visits"] for row in offline["zones"])
    )
    assert not spied, "a camera user read the analytics events"

    # Metrics of the restarted matcher.
    assert scraped["/healthz"].startswith("ok")
    assert scraped["/readyz"].startswith("ok")
    for name in METRICS:
        assert name in scraped["/metrics"]
