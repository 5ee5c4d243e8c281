"""Alerts in the running matcher: a real Mosquitto, `cblrs matcher --site` with alert rules,
killed and restarted, and a real HTTP receiver checking each webhook's HMAC signature.

The site (``cblrs site init`` of WILDTRACK) carries a ``camera_offline`` rule for CVLab1 and a
webhook whose secret is in a 0600 file. CVLab1 is silent at first, so the episode fires: the
receiver gets it once, signed, and the viewer login reads it on ``cblrs/1/alerts``. The
matcher is killed (SIGKILL) and restarted on the same database while the episode is open: it
must not fire again. Then CVLab1 sends (as its own broker user) and the episode clears, once.
A camera login cannot publish on the alerts topic.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_runtime_transport import Collector  # tests/runtime is on sys.path (rootdir-relative)
from waiting import wait_until

from cblrs.cli.main import main
from cblrs.detections import CameraMessage
from cblrs.runtime.outputs.events import decode_alert
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import alerts_topic, detections_topic
from cblrs.runtime.wire import encode_message

pytestmark = [pytest.mark.mqtt]

REPO = Path(__file__).resolve().parents[2]
MATCHER = "matcher1"
SECRET = b"a webhook secret for the test"
RULE = {"name": "down", "kind": "camera_offline", "camera": "CVLab1", "for_s": 1}


class Receiver:
    """A local HTTP server recording each POST and whether its signature is right."""

    def __init__(self, secret: bytes):
        self.posts: list[dict] = []
        self._lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers["Content-Length"]))
                timestamp = self.headers["X-Cblrs-Timestamp"]
                expected = "sha256=" + hmac.new(secret, timestamp.encode() + b"." + body,
                                                hashlib.sha256).hexdigest()
                valid = hmac.compare_digest(expected, self.headers["X-Cblrs-Signature"])
                with receiver._lock:
                    receiver.posts.append({"valid": valid, "body": json.loads(body),
                                           "episode": self.headers["X-Cblrs-Episode"],
                                           "age_s": time.time() - float(timestamp)})
                self.send_response(200 if valid else 401)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/hook"

    def episodes(self) -> list[str]:
        with self._lock:
            return [post["episode"] for post in self.posts]

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture(scope="module")
def wildtrack_site(wildtrack_root, tmp_path_factory) -> dict:
    """`cblrs site init` of WILDTRACK with the places of sites/wildtrack.yaml."""
    folder = tmp_path_factory.mktemp("alerts-site")
    path = folder / "base.yaml"
    assert main(["site", "init", str(wildtrack_root), "--out", str(path)]) == 0
    document = yaml.safe_load(path.read_text())
    document["places"] = yaml.safe_load((REPO / "sites/wildtrack.yaml").read_text())["places"]
    return document


def write_site(base: dict, folder: Path, url: str, rules=(RULE,)) -> Path:
    secret = folder / "ops.secret"
    secret.write_bytes(SECRET)
    secret.chmod(0o600)
    document = {**base, "alerts": {
        "rules": list(rules),
        "webhooks": [{"name": "ops", "url": url, "secret_file": "ops.secret", "timeout_s": 2,
                      "retries": 3, "backoff_s": 0.2, "max_backoff_s": 1}],
    }}
    path = folder / "site.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def start_matcher(site: Path, database: Path, broker, window: str = "1") -> subprocess.Popen:
    command = [
        sys.executable, "-m", "cblrs.cli.main", "matcher", "--site", str(site),
        "--db", str(database), "--broker", f"127.0.0.1:{broker.port}",
        "--username", MATCHER, "--password-file", str(broker.files.password_files[MATCHER]),
        "--window", window,
    ]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def read_db(database: Path, sql: str) -> list[tuple]:
    """The rows of a read-only query (none while the matcher has not created the file)."""
    if not database.exists():
        return []
    with sqlite3.connect(f"file:{database}?mode=ro", uri=True, timeout=5) as connection:
        try:
            return connection.execute(sql).fetchall()
        except sqlite3.OperationalError as error:  # the tables are being created
            if "no such table" in str(error):
                return []
            raise


def alert_clock(database: Path) -> float:
    rows = read_db(database, "SELECT value FROM meta WHERE key = 'alert_state'")
    return (json.loads(rows[0][0])["clock"] or 0.0) if rows else 0.0


def delivered(database: Path) -> dict[str, list[str]]:
    rows = read_db(database, "SELECT episode || ' ' || state, delivered FROM alerts")
    return {episode: json.loads(names) for episode, names in rows}


class Heartbeat:
    """CVLab1 as its own broker user, sending an empty frame every 0.2 s."""

    def __init__(self, broker):
        self.transport = MqttTransport("CVLab1", broker.settings("CVLab1"), persistent=False)
        self.transport.connect()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        sequence = 0
        while not self._stop.wait(0.2):
            message = CameraMessage(
                camera_id="CVLab1", sequence=sequence, timestamp=time.time(), frame=sequence,
                xyxy=np.zeros((0, 4)), confidence=np.zeros(0),
                class_id=np.zeros(0, dtype=np.int64), colour=np.zeros((0, 3), dtype=np.int64))
            self.transport.publish(detections_topic(1, "CVLab1"), encode_message(message, 1))
            sequence += 1

    def close(self) -> None:
        self._stop.set()
        self.thread.join(2)
        self.transport.close(timeout=1)


def test_an_episode_fires_once_and_clears_once_across_a_matcher_kill(
        wildtrack_site, start_mosquitto, tmp_path):
    names = [camera["name"] for camera in wildtrack_site["cameras"]]
    broker = start_mosquitto(cameras=names, matchers=[MATCHER], plane_ids=(1,))
    receiver = Receiver(SECRET)
    site = write_site(wildtrack_site, tmp_path, receiver.url)
    database = tmp_path / "matcher.db"
    viewer = MqttTransport("viewer", broker.settings("viewer"), persistent=False)
    alerts = Collector()
    viewer.subscribe(alerts_topic(1), alerts)
    viewer.connect()
    processes: list[subprocess.Popen] = []
    heartbeat = None
    try:
        # A camera login cannot publish alerts: the broker refuses, the viewer sees nothing.
        camera = MqttTransport("CVLab2", broker.settings("CVLab2"), persistent=False)
        camera.connect()
        camera.publish(alerts_topic(1), b'{"schema": "cblrs.alerts/1", "forged": true}')
        assert camera.flush(5)
        assert camera.refused_publishes == 1
        camera.close(timeout=1)

        processes.append(start_matcher(site, database, broker))
        wait_until(lambda: "down/CVLab1/1 fired" in receiver.episodes()
                   or processes[0].poll() is not None, 90, "the webhook's 'fired'")
        assert processes[0].poll() is None, processes[0].communicate()[1]
        first = receiver.posts[0]
        assert first["valid"] and 0 <= first["age_s"] < 30
        assert first["body"]["episode"] == "down/CVLab1/1" and first["body"]["state"] == "fired"
        assert first["body"]["kind"] == "camera_offline" and first["body"]["subject"] == "CVLab1"
        assert first["body"]["plane"] == 1
        # The viewer reads it on the backbone, with the episode in the active list.
        wait_until(lambda: alerts.deliveries, 10, "the alert on the backbone")
        published = decode_alert(alerts.deliveries[0].payload)
        assert (published.episode, published.state) == ("down/CVLab1/1", "fired")
        assert [active.episode for active in published.active] == ["down/CVLab1/1"]
        # Committed as delivered to both before the kill (else a re-send would be right).
        wait_until(lambda: sorted(delivered(database).get("down/CVLab1/1 fired", [])) == [
            "cblrs/backbone", "ops"], 10, "the alert marked delivered")

        processes[0].send_signal(signal.SIGKILL)
        processes[0].wait(10)
        restarted_at = time.time()
        processes.append(start_matcher(site, database, broker))
        # The restarted matcher evaluates the rule for several seconds (its clock, committed
        # with the episodes, moves past for_s beyond the restart) without firing it again.
        wait_until(lambda: alert_clock(database) > restarted_at + 3
                   or processes[1].poll() is not None, 90, "the restarted matcher's alerts")
        assert processes[1].poll() is None, processes[1].communicate()[1]
        assert receiver.episodes() == ["down/CVLab1/1 fired"]

        heartbeat = Heartbeat(broker)  # CVLab1 comes back: the episode clears
        wait_until(lambda: "down/CVLab1/1 cleared" in receiver.episodes(), 90,
                   "the webhook's 'cleared'")
        wait_until(lambda: len(alerts.deliveries) >= 2, 10, "the 'cleared' on the backbone")
        cleared = decode_alert(alerts.deliveries[-1].payload)
        assert (cleared.episode, cleared.state, cleared.active) == (
            "down/CVLab1/1", "cleared", [])
        wait_until(lambda: sorted(delivered(database).get("down/CVLab1/1 cleared", [])) == [
            "cblrs/backbone", "ops"], 10, "the 'cleared' marked delivered")
        assert receiver.episodes() == ["down/CVLab1/1 fired", "down/CVLab1/1 cleared"]
        assert all(post["valid"] for post in receiver.posts)
        assert [(item.episode, item.state) for item in map(
            decode_alert, (d.payload for d in alerts.deliveries))] == [
            ("down/CVLab1/1", "fired"), ("down/CVLab1/1", "cleared")]
        processes[1].send_signal(signal.SIGINT)
        _, err = processes[1].communicate(timeout=30)
        assert processes[1].returncode == 0, err
        assert "counting lines, 1 alert rules" in err
    finally:
        if heartbeat is not None:
            heartbeat.close()
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()
        viewer.close(timeout=1)
        receiver.close()


def test_live_counts_fire_the_line_and_zone_rules(wildtrack_root, wildtrack_site,
                                                 start_mosquitto, tmp_path):
    """Seven WILDTRACK cameras replay 30 s of the scene (~5x) through the broker: every line
    the matcher counted crossings on fires its line-count rule (more than 0 in 3 s) and clears
    it 3 s after, once each; an occupancy rule fires only on zones people entered."""
    from test_runtime_online_analytics import start_cameras

    from cblrs.datasets import load_scene
    from cblrs.site import load_site

    places = wildtrack_site["places"]
    rules = [{"name": f"rush {line['name']}", "kind": "line_count", "line": line["name"],
              "above": 0, "per_s": 3} for line in places["lines"]]
    rules += [{"name": f"busy {zone['name']}", "kind": "occupancy", "zone": zone["name"],
               "above": 0} for zone in places["zones"]]
    names = [camera["name"] for camera in wildtrack_site["cameras"]]
    broker = start_mosquitto(cameras=names, matchers=[MATCHER], plane_ids=(1,))
    receiver = Receiver(SECRET)
    site_path = write_site(wildtrack_site, tmp_path, receiver.url, rules)
    site = load_site(site_path)
    scene = load_scene(wildtrack_root).select_frames(0, 295)
    case = {"scene": scene,
            "references": [site.render_reference(name) for name in scene.camera_names]}
    database = tmp_path / "matcher.db"
    matcher = start_matcher(site_path, database, broker, window="5")
    try:
        wait_until(lambda: alert_clock(database) > 0 or matcher.poll() is not None, 90,
                   "the matcher's first alert observation")
        assert matcher.poll() is None, matcher.communicate()[1]
        for thread in start_cameras(case, broker, float(int(time.time()) - 600)):
            thread.join(60)

        def counted(kind: str) -> set[str]:
            return {place for (place,) in read_db(
                database, f"SELECT DISTINCT place FROM events WHERE kind = '{kind}'")}

        wait_until(lambda: read_db(database, "SELECT COUNT(*) FROM inbox WHERE status = "
                                   "'pending'") == [(0,)] and counted("line_crossed"), 60,
                   "every message tracked and crossings counted")
        crossed = counted("line_crossed")
        expected = {f"rush {line}/{line}/1 {state}" for line in crossed
                    for state in ("fired", "cleared")}
        # The last crossing's rule clears 3 s after it (wall clock), at the latest.
        wait_until(lambda: expected <= set(receiver.episodes()), 90,
                   "each counted line's rule to fire and clear")
        assert all(post["valid"] for post in receiver.posts)
        episodes = receiver.episodes()
        assert len(episodes) == len(set(episodes)), episodes  # each (episode, state) once
        lines_fired = {post["body"]["subject"] for post in receiver.posts
                       if post["body"]["kind"] == "line_count"}
        assert lines_fired == crossed  # no line fired that the matcher did not count
        zones_fired = {post["body"]["subject"] for post in receiver.posts
                       if post["body"]["kind"] == "occupancy"}
        assert zones_fired and zones_fired <= counted("zone_entered")
    finally:
        if matcher.poll() is None:
            matcher.kill()
            matcher.communicate()
        receiver.close()
