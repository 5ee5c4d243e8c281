"""The fault tests' plant: a real Mosquitto, ``cblrs matcher`` and ``cblrs camera``
processes on two WILDTRACK cameras (test_runtime_faults*.py), and their helpers. The
fixtures `plant` and `fault_references` reach the tests through conftest.py.

Scaled down to stay quick on two cores: two cameras (CVLab1, CVLab2), 40 annotated frames
each (80 messages); a queue cap of a few kilobytes stands in for the 100 000-message one.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from waiting import store_counter, wait_until

from cblrs.datasets import load_scene
from cblrs.pipeline import render_scene_references
from cblrs.runtime.matcher.store import RuntimeStore

CAMERAS = ("CVLab1", "CVLab2")
FRAMES = "0:195"  # 40 annotated frames
PER_CAMERA = 40
TOTAL = PER_CAMERA * len(CAMERAS)
EPOCH = float(int(time.time()) - 600)  # every capture time in the recent past
ENVIRONMENT = {**os.environ, "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def fault_references(wildtrack_root, tmp_path_factory) -> Path:
    """Reference PNGs of the two cameras (the matcher's camera list)."""
    scene = load_scene(wildtrack_root).select_frames(0, 195)
    folder = tmp_path_factory.mktemp("fault-references")
    for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=True):
        if camera.name in CAMERAS:
            reference.save(folder / f"{camera.name}.png")
    return folder


class Plant:
    """One broker plus the command lines of the cameras and the matcher of plane 1."""

    def __init__(self, broker, references: Path, root: Path, wildtrack_root: Path):
        self.broker = broker
        self.references = references
        self.root = root
        self.wildtrack = wildtrack_root
        self.processes: list[subprocess.Popen] = []

    def login(self, user: str) -> list[str]:
        return ["--broker", f"127.0.0.1:{self.broker.port}", "--username", user,
                "--password-file", str(self.broker.files.password_files[user])]

    def camera(self, name: str, *extra: str, replay: bool = True) -> list[str]:
        """A camera replaying its 40 frames, or (``replay=False``) one with nothing new to
        send: it only delivers what its spool holds."""
        if replay:
            source = ["--dataset", str(self.wildtrack), "--frames", FRAMES]
        else:
            nothing = self.root / "no-detections.txt"
            nothing.write_text("")
            source = ["--detections", str(nothing), "--fps", "2"]
        return [sys.executable, "-m", "cblrs.cli.main", "camera", "--camera", name, *source,
                "--references", str(self.references), "--epoch", str(EPOCH), "--spool",
                str(self.root / f"{name}.spool"), "--json", *self.login(name), *extra]

    def matcher(self, database: Path, *extra: str, user: str = "matcher1") -> list[str]:
        return [sys.executable, "-m", "cblrs.cli.main", "matcher", "--references",
                str(self.references), "--db", str(database), "--json", "--window", "10",
                *self.login(user), *extra]

    def start(self, command: list[str], **options) -> subprocess.Popen:
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                   text=True, env=ENVIRONMENT, **options)
        self.processes.append(process)
        return process

    def run(self, command: list[str], timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run(command, capture_output=True, text=True, env=ENVIRONMENT,
                              timeout=timeout)

    def stop_all(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.kill()
                process.communicate()


@pytest.fixture
def plant(start_mosquitto, fault_references, tmp_path, wildtrack_root):
    made: list[Plant] = []

    def make(**broker_options) -> Plant:
        broker = start_mosquitto(cameras=CAMERAS, matchers=("matcher1",), plane_ids=(1,),
                                 **broker_options)
        made.append(Plant(broker, fault_references, tmp_path, wildtrack_root))
        return made[-1]

    yield make
    for item in made:
        item.stop_all()


def finish(process: subprocess.Popen, timeout: float = 60) -> tuple[int, str, str]:
    out, err = process.communicate(timeout=timeout)
    return process.returncode, out, err


def assert_all_stored_once(database: Path) -> dict:
    """Every (camera, sequence) of both replays is in the inbox, and was tracked once."""
    with RuntimeStore(database, read_only=True) as store:
        keys = {(item.message.camera_id, item.message.sequence) for item in store.messages()}
        counters = store.counters()
        statuses = store.status_counts()
    expected = {(name, sequence) for name in CAMERAS for sequence in range(PER_CAMERA)}
    assert keys == expected, f"lost: {sorted(expected - keys)[:10]}"
    assert counters["processed"] + counters.get("late", 0) == TOTAL, counters
    assert statuses.get("pending", 0) == 0, statuses
    return counters


counter = store_counter
"""A counter of a running matcher's database (0 while its matcher is still creating it)."""


def spool_rows(path: Path, state: int | None = None) -> int:
    """Messages in a camera's spool file (0 while it does not exist yet); with ``state``,
    those in that state (2: acknowledged by the broker)."""
    if not path.exists():
        return 0
    where, parameters = ("", ()) if state is None else (" WHERE state = ?", (state,))
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as connection:
            return connection.execute(f"SELECT COUNT(*) FROM outbox{where}",
                                      parameters).fetchone()[0]
    except sqlite3.OperationalError:  # created, tables not yet
        return 0


def broker_saves(plant: Plant) -> int:
    """How many times the broker has begun saving its database (it logs each save)."""
    return plant.broker.process.log_path.read_text().count("Saving in-memory database")


def wait_matcher_online(plant: Plant, since: float, timeout: float = 60) -> None:
    """Wait for the matcher's retained "online" stamped after ``since``: it then holds its
    database and the plane's lease and has subscribed."""
    from cblrs.runtime.transport.mqtt_transport import MqttTransport
    from cblrs.runtime.transport.topics import matcher_status_filter
    from cblrs.runtime.wire import decode_status

    seen: list = []
    viewer = MqttTransport("viewer", plant.broker.settings("viewer"), persistent=False)
    viewer.subscribe(matcher_status_filter(1), lambda delivery: (
        seen.append(decode_status(delivery.payload)), delivery.ack()))
    viewer.connect()
    try:
        wait_until(lambda: any(status.state == "online" and (status.timestamp or 0) >= since
                               for status in seen), timeout, "the matcher to be online")
    finally:
        viewer.close()


def one_sentence(err: str) -> str:
    """The error line of a failed command; no traceback allowed."""
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1, err
    return errors[0]


# -- item 1 ----------------------------------------------------------------------------------
