"""A real multi-plane run for the dashboard tests: two planes of the synthetic city, a secured
backbone (Mosquitto, or nats-server with a site id), one ``cblrs matcher`` process per plane,
a ``cblrs linker`` process, and the cameras' frames published by the test with each camera's
own login (the colours its reference would give: the ground truth's positions encoded on the
camera's plane, so no reference needs rendering).

Also a reader of the dashboard's Server-Sent-Events stream, collecting its messages in a
thread.
"""

from __future__ import annotations

import http.client
import json
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import yaml
from dashboard_helpers import cblrs_command, first_headers

from cblrs.datasets.city import CityScenes, city_scenes, city_site_document, street_world
from cblrs.detections import CameraMessage
from cblrs.runtime.transport.topics import detections_topic
from cblrs.runtime.wire import encode_message

PLANES = (1, 2)
FRAMES = range(100, 250)
"""15 s of the city at 10 fps: people and cars on both planes, some crossing between them."""
SITE_ID = "south"


def city_two_planes(folder: Path) -> tuple[Path, CityScenes]:
    """The city's first two planes (their cameras, places and link) as a site file."""
    scenes = city_scenes(street_world(seed=3, people=6, cars=2, wanderers=0, spawn_s=4.0,
                                      max_trip_m=60.0))
    document = city_site_document(scenes.spec, name="street")
    document["planes"] = [plane for plane in document["planes"] if plane["id"] in PLANES]
    document["cameras"] = [camera for camera in document["cameras"]
                           if camera["plane"] in PLANES]
    for kind in ("zones", "lines"):
        document["places"][kind] = [place for place in document["places"].get(kind, [])
                                    if place.get("plane_id") in PLANES]
    document["links"] = [link for link in document["links"]
                         if set(link["planes"]) <= set(PLANES)]
    path = folder / "street.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path, scenes


def camera_names(scenes: CityScenes) -> list[str]:
    return [camera.name for plane in PLANES for camera in scenes.planes[plane].cameras]


def camera_frames(scenes: CityScenes, epoch: float) -> list[list[tuple[str, bytes]]]:
    """Per frame, every camera's ``(topic, payload)`` on its plane."""
    frames: list[list[tuple[str, bytes]]] = []
    for index in FRAMES:
        messages = []
        for plane in PLANES:
            scene = scenes.planes[plane]
            spec = scenes.spec.planes.by_id(plane)
            truth = scene.ground_truth[scene.ground_truth.frame == scene.frames[index]]
            where = dict(zip(truth.track_id.tolist(), truth.world_xy.tolist(), strict=True))
            for camera_index, camera in enumerate(scene.cameras):
                boxes = scene.detections[index][camera_index]
                keep = np.array([int(obj) in where for obj in boxes.object_id], dtype=bool)
                boxes = boxes[keep]
                world = np.array([where[int(obj)] for obj in boxes.object_id]).reshape(-1, 2)
                colours, valid = spec.encode(world)
                message = CameraMessage(
                    camera.name, index - FRAMES[0], epoch + float(scene.timestamps[index]),
                    int(scene.frames[index]), boxes.xyxy[valid], boxes.confidence[valid],
                    boxes.class_id[valid], colours[valid].astype(np.int64))
                messages.append((detections_topic(plane, camera.name),
                                 encode_message(message, plane)))
        frames.append(messages)
    return frames


class Processes:
    """Started processes, stopped (SIGTERM, then kill) at the end."""

    def __init__(self) -> None:
        self.started: list[subprocess.Popen] = []

    def start(self, *arguments: str) -> subprocess.Popen:
        process = subprocess.Popen(cblrs_command(*arguments), stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True)
        self.started.append(process)
        return process

    def stop(self) -> None:
        for process in self.started:
            if process.poll() is None:
                process.terminate()
        for process in self.started:
            try:
                process.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.communicate()


def request(url: str, path: str, method: str = "GET", headers: dict | None = None,
            body: str | None = None) -> tuple[int, dict[str, str], bytes]:
    """One request, no redirect followed: (status, lower-cased headers, body)."""
    parts = urlsplit(url)
    connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)
    try:
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        data = response.read()
        return response.status, first_headers(response), data
    finally:
        connection.close()


def log_in(url: str, user: tuple[str, str]) -> dict[str, str]:
    """The headers of ``user``'s session (a login of the dashboard's users file): its cookie
    and its page token."""
    status, headers, body = request(url, "/api/login", "POST", {
        "Content-Type": "application/json", "Origin": url.rstrip("/")},
        json.dumps({"user": user[0], "password": user[1]}))
    assert status == 200, body
    return {"Cookie": headers["set-cookie"].split(";")[0],
            "X-CBLRS-Session": json.loads(body)["session"]}


class Stream:
    """The dashboard's live stream read in a thread: every message, in order."""

    def __init__(self, url: str, path: str, session: dict[str, str]):
        parts = urlsplit(url)
        self.connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=300)
        self.connection.request("GET", path, headers=session)
        self.response = self.connection.getresponse()
        self.status = self.response.status
        self.messages: list[dict] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, daemon=True)
        if self.status == 200:
            self._thread.start()

    def _read(self) -> None:
        try:
            for raw in self.response:
                line = raw.decode().strip()
                if line.startswith("data: "):
                    with self._lock:
                        self.messages.append(json.loads(line[6:]))
        except (OSError, ValueError, AttributeError, http.client.HTTPException):
            return  # closed (http.client drops its file on close: AttributeError)

    def snapshot(self) -> list[dict]:
        with self._lock:
            return list(self.messages)

    def wait(self, predicate: Callable[[list[dict]], object], timeout: float, what: str
             ) -> list[dict]:
        deadline = time.monotonic() + timeout
        while True:
            messages = self.snapshot()
            if predicate(messages):
                return messages
            if time.monotonic() > deadline:
                kinds: dict[str, int] = {}
                for message in messages:
                    key = f"{message.get('type')}/{message.get('plane')}"
                    kinds[key] = kinds.get(key, 0) + 1
                raise AssertionError(f"timed out after {timeout} s waiting for {what}; "
                                     f"received {kinds}")
            time.sleep(0.1)

    def close(self) -> None:
        self.connection.close()
