"""Pseudo coordinates end to end: no real coordinate on the wire or in the matcher's database.

Everything runs as a user runs it: ``cblrs pseudo keygen``, ``cblrs render --site --key``,
``cblrs pseudo site``, a real Mosquitto (started by the test on a free loopback port), the
matcher (``cblrs matcher --site PSEUDO``, no key) and three cameras (``cblrs camera
--reference``) as separate processes, and a subscriber on ``cblrs/#`` that records every
message the broker carries. Then every coordinate that was transmitted or stored is checked
against where the people and the site really are:

* **people**: each detection's colour decoded with the *real* plane (what anyone who knows
  the site's plane would do), each track row (wire and database), each event position (wire
  and database) and each track in the tracker's saved state is compared with the true
  position of the person it is — found by mapping the value back with the key, which the
  test holds and the services do not. A value within 0.5 m of its person's true position
  (detections: within 5 mm of where the plain reference puts that person) is a leak;
* **the site**: every pair of numbers anywhere in the database and in every message is
  compared with the site's own points (camera positions, the places' corners and ends); one
  within 1 cm is a leak.

The same run in plain mode (real site, plain references) must find leaks of every kind, so
the check can fail; in pseudo mode it must find none.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from waiting import wait_until

from cblrs.datasets import load_scene
from cblrs.privacy import PseudoKey
from cblrs.reference import load_reference
from cblrs.runtime.outputs.events import decode_event
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import matcher_status_topic
from cblrs.runtime.wire import decode_status, decode_tracks
from cblrs.site import load_site

pytestmark = [pytest.mark.mqtt, pytest.mark.slow]

CAMERAS = ("CVLab1", "CVLab3", "IDIAP1")
FRAMES = "0:150"
FRAME_RATE = 10.0  # WILDTRACK's native frame numbers: 10 per second
PERSON_M = 0.5
SITE_M = 0.01
# Odd numbers, so that no counter or setting in a message can equal a corner by chance.
PLACES = {
    "zones": [{"name": "crossing",
               "polygon": [[1.137, 11.523], [6.541, 11.523], [6.541, 15.561], [1.137, 15.561]]}],
    "lines": [{"name": "middle", "start": [-2.473, 6.029], "end": [8.519, 6.029]},
              {"name": "north", "start": [-1.951, 17.013], "end": [8.547, 17.013]}],
}


def _command(*arguments: str) -> list[str]:
    return [sys.executable, "-m", "cblrs.cli.main", *arguments]


def _run(*arguments: str) -> None:
    done = subprocess.run(_command(*arguments), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr


@dataclass
class Leaks:
    """What the check found: values compared and leaks, per kind."""

    checked: dict[str, int] = field(default_factory=dict)
    leaked: dict[str, int] = field(default_factory=dict)
    examples: list[str] = field(default_factory=list)

    def add(self, kind: str, leak: bool, what: str) -> None:
        self.checked[kind] = self.checked.get(kind, 0) + 1
        self.leaked[kind] = self.leaked.get(kind, 0) + int(leak)
        if leak and len(self.examples) < 5:
            self.examples.append(f"{kind}: {what}")


@pytest.mark.parametrize("mode", ["plain", "pseudo"])
def test_no_real_coordinate_on_the_wire_or_in_the_database(
    mode, wildtrack_root, mosquitto, tmp_path
):
    site_path = tmp_path / "site.yaml"
    _run("site", "init", "--dataset", str(wildtrack_root), "--out", str(site_path))
    document = yaml.safe_load(site_path.read_text())
    document["places"] = PLACES
    document["cameras"] = [camera for camera in document["cameras"] if camera["name"] in CAMERAS]
    site_path.write_text(yaml.safe_dump(document))
    key = None
    references = tmp_path / "refs"
    if mode == "pseudo":
        key_path = tmp_path / "site.key"
        _run("pseudo", "keygen", "--out", str(key_path))
        key = PseudoKey.load(key_path)
        _run("render", "--site", str(site_path), "--key", str(key_path), "--out", str(references),
             "--quiet")
        matcher_site = tmp_path / "pseudo-site.yaml"
        _run("pseudo", "site", str(site_path), "--key", str(key_path), "--out", str(matcher_site))
    else:
        _run("render", "--site", str(site_path), "--out", str(references), "--quiet")
        matcher_site = site_path
    messages: list[tuple[str, bytes]] = []
    lock = threading.Lock()
    online = threading.Event()
    sniffer = MqttTransport(f"sniffer-{mode}", mosquitto.settings(), persistent=False)

    def record(delivery) -> None:
        with lock:
            messages.append((delivery.topic, bytes(delivery.payload)))
        if delivery.topic == matcher_status_topic(1, f"matcher-{mode}") and \
                decode_status(delivery.payload).state == "online":
            online.set()
        delivery.ack()

    sniffer.subscribe("cblrs/#", record)
    sniffer.connect()
    database = tmp_path / "matcher.db"
    matcher = subprocess.Popen(
        _command("matcher", "--site", str(matcher_site), "--db", str(database),
                 "--client-id", f"matcher-{mode}",
                 "--broker", f"127.0.0.1:{mosquitto.port}", "--window", "120",
                 "--until-cameras-offline"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    cameras: list[subprocess.Popen] = []
    epoch = float(int(time.time()) - 300)
    try:
        wait_until(lambda: online.is_set() or matcher.poll() is not None, 60,
                   "the matcher to come online")
        assert matcher.poll() is None, matcher.communicate()[1]
        for name in CAMERAS:
            cameras.append(subprocess.Popen(
                _command("camera", "--dataset", str(wildtrack_root), "--camera", name,
                         "--reference", str(references / f"{name}.png"), "--frames", FRAMES,
                         "--epoch", str(epoch), "--broker", f"127.0.0.1:{mosquitto.port}",
                         "--quiet"),
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            ))
        for camera in cameras:
            _, error = camera.communicate(timeout=180)

            assert camera.returncode == 0, error
        out, err = matcher.communicate(timeout=180)
        assert matcher.returncode == 0, err
        # The matcher's last words (offline status, final live summary) reach the sniffer.
        wait_until(lambda: any(topic.endswith(f"matchers/matcher-{mode}/status")
                               and decode_status(payload).state == "offline"
                               for topic, payload in list(messages)), 30, "the matcher's end")
    finally:
        for process in [matcher, *cameras]:
            if process.poll() is None:
                process.kill()
        sniffer.close()
    assert "rejected 0" in out, out

    leaks = find_leaks(wildtrack_root, site_path, references, key, epoch, messages, database)
    kinds = ("detections", "tracks", "events", "site")
    assert all(leaks.checked.get(kind, 0) > 0 for kind in kinds), leaks.checked
    if mode == "plain":
        # The check sees real coordinates where they are: it can fail.
        assert leaks.leaked["detections"] > 0.9 * leaks.checked["detections"], leaks
        assert leaks.leaked["tracks"] > 0.9 * leaks.checked["tracks"], leaks
        assert leaks.leaked["events"] > 0.9 * leaks.checked["events"], leaks
        assert leaks.leaked["site"] > 0, leaks
    else:
        assert sum(leaks.leaked.values()) == 0, leaks


# ---------------------------------------------------------------------------- the check


def find_leaks(
    dataset: Path, site_path: Path, references: Path, key: PseudoKey | None, epoch: float,
    messages: list[tuple[str, bytes]], database: Path,
) -> Leaks:
    """Every transmitted and stored coordinate against the true positions (module doc)."""
    scene = load_scene(dataset)
    truth = scene.ground_truth
    site = load_site(site_path)
    real_planes = site.require_planes("the check")
    sent_references = {name: load_reference(references / f"{name}.png") for name in CAMERAS}
    landmarks = _site_points(site)
    leaks = Leaks()

    def to_site(points: np.ndarray) -> np.ndarray:
        return points if key is None else key.to_site(points)

    def person(kind: str, frame: int, value: np.ndarray) -> None:
        """A person's position as stored: a leak if it is where that person really is."""
        rows = truth.frame == _annotated(frame)
        if not rows.any():
            return
        true_xy = truth.world_xy[rows]
        estimate = to_site(value[None])[0]
        nearest = np.argmin(np.linalg.norm(true_xy - estimate, axis=1))
        if np.linalg.norm(true_xy[nearest] - estimate) > 1.0:
            return  # no person there (a false track): nothing of anyone's to leak
        distance = float(np.linalg.norm(true_xy[nearest] - value))
        leaks.add(kind, distance < PERSON_M, f"frame {frame} {value.round(2).tolist()} is "
                  f"{distance:.2f} m from a person")

    def detection(camera: str, colour: list[int]) -> None:
        """A colour read with the real plane: a leak if it says where the person is."""
        colours = np.array([colour])
        naive, naive_valid, _ = real_planes.decode(colours)
        located, valid, _ = sent_references[camera].planes.decode(colours)
        if not valid[0]:
            return
        where = to_site(located)[0]
        leak = bool(naive_valid[0]) and float(np.linalg.norm(naive[0] - where)) < 0.005
        leaks.add("detections", leak, f"{camera} colour {colour} decodes to {where.round(2)}")

    def site_numbers(where: str, value: Any) -> None:
        for pair in _pairs(value):
            close = np.linalg.norm(landmarks - pair, axis=1).min() < SITE_M
            leaks.add("site", bool(close), f"{where}: {pair.tolist()}")

    for topic, payload in messages:
        if not payload:
            continue  # a camera clearing a retained message at its start
        data = json.loads(payload)
        site_numbers(topic, data)
        if topic.endswith("/detections"):
            for item in data["detections"]:
                detection(data["camera"], item["colour"])
        elif topic.endswith("/tracks"):
            update = decode_tracks(payload)
            for frame, world_xy in zip(update.tracks.frame.tolist(), update.tracks.world_xy,
                                       strict=True):
                person("tracks", frame, world_xy)
        elif topic.endswith("/events"):
            event = decode_event(payload)
            if event.world_xy is not None:
                person("events", _frame(event.timestamp, epoch), np.array(event.world_xy))

    connection = sqlite3.connect(database)
    try:
        for table in [name for (name,) in connection.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")]:
            columns = [row[1] for row in connection.execute(f"PRAGMA table_info({table})")]
            for row in connection.execute(f"SELECT * FROM {table}"):
                values = dict(zip(columns, row, strict=True))
                for name, value in values.items():
                    if isinstance(value, str) and value[:1] in "[{":
                        site_numbers(f"{table}.{name}", json.loads(value))
                if {"x", "y"} <= set(values):
                    site_numbers(table, [values["x"], values["y"]])
                if table == "tracks":
                    person("tracks", values["frame"], np.array([values["x"], values["y"]]))
                elif table == "inbox":
                    for colour in json.loads(values["body"])["colour"]:
                        detection(values["camera_id"], colour)
                elif table == "events":
                    body = json.loads(values["body"])
                    if body.get("world_xy") is not None:
                        person("events", _frame(body["timestamp"], epoch),
                               np.array(body["world_xy"]))
                elif table == "meta" and values["key"] == "matcher_state":
                    state = json.loads(values["value"])
                    frame = _frame(state["time"], epoch) if state["time"] is not None else None
                    for row in state["state"] if frame is not None else []:
                        person("state", frame, np.array(row[:2]))
    finally:
        connection.close()
    return leaks


def _annotated(frame: int) -> int:
    """The annotated WILDTRACK frame (every 5th) nearest to a native frame number."""
    return 5 * round(frame / 5)


def _frame(timestamp: float, epoch: float) -> int:
    return round((timestamp - epoch) * FRAME_RATE)


def _site_points(site) -> np.ndarray:
    points = [position[:2] for position in site.camera_positions().values()]
    points += [point for zone in site.places.zones for point in zone.polygon]
    points += [point for line in site.places.lines for point in (line.start, line.end)]
    return np.array(points, dtype=float)


def _pairs(value: Any) -> list[np.ndarray]:
    """Every two neighbouring numbers of every list in a JSON value (and of a dict's values)."""
    pairs: list[np.ndarray] = []
    if isinstance(value, dict):
        numbers = [item for item in value.values() if _is_number(item)]
        pairs += [np.array(numbers[i:i + 2], float) for i in range(len(numbers) - 1)]
        for item in value.values():
            pairs += _pairs(item)
    elif isinstance(value, list):
        numbers = [item for item in value if _is_number(item)]
        pairs += [np.array(numbers[i:i + 2], float) for i in range(len(numbers) - 1)]
        for item in value:
            if isinstance(item, dict | list):
                pairs += _pairs(item)
    return pairs


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)
