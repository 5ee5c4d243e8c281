"""Fault tests of issue 10: real Mosquitto, real ``cblrs camera`` / ``cblrs matcher``
processes, real WILDTRACK detections. Each test breaks one thing the way an operator or a
machine would and asserts that no acknowledged message is lost (or that the command refuses,
in one sentence, before anything is acknowledged).

Scaled down to stay quick on two cores: two cameras (CVLab1, CVLab2), 40 annotated frames
each (80 messages); a queue cap of a few kilobytes stands in for the 100 000-message one.
"What cblrs guarantees" in docs/services.md names the test behind each of its lines.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from waiting import wait_until

from cblrs.datasets import load_scene
from cblrs.pipeline import render_scene_references
from cblrs.runtime.store import RuntimeStore

pytestmark = pytest.mark.mqtt

CAMERAS = ("CVLab1", "CVLab2")
FRAMES = "0:195"  # 40 annotated frames
PER_CAMERA = 40
TOTAL = PER_CAMERA * len(CAMERAS)
EPOCH = float(int(time.time()) - 600)  # every capture time in the recent past
ENVIRONMENT = {**os.environ, "PYTHONUNBUFFERED": "1"}


@pytest.fixture(scope="module")
def references(wildtrack_root, tmp_path_factory) -> Path:
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
def plant(start_mosquitto, references, tmp_path, wildtrack_root):
    made: list[Plant] = []

    def make(**broker_options) -> Plant:
        broker = start_mosquitto(cameras=CAMERAS, matchers=("matcher1",), plane_ids=(1,),
                                 **broker_options)
        made.append(Plant(broker, references, tmp_path, wildtrack_root))
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


def counter(database: Path, name: str) -> int:
    """A counter of a running matcher's database (0 while it is being created)."""
    try:
        with RuntimeStore(database, read_only=True) as store:
            return store.counters().get(name, 0)
    except Exception:  # not there yet, or its tables not yet written
        return 0


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
    from cblrs.runtime.mqtt_transport import MqttTransport
    from cblrs.runtime.topics import matcher_status_filter
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


def test_item1_a_full_broker_queue_loses_nothing(plant, tmp_path):
    """Mosquitto drops messages for a full queue after acknowledging them; the cameras'
    spools send again what the matcher does not confirm."""
    plant = plant(queue_bytes=4096)  # about two WILDTRACK messages
    database = tmp_path / "plane1.db"
    prepared = plant.run(plant.matcher(database, "--prepare"))
    assert prepared.returncode == 0, prepared.stderr
    cameras = [plant.start(plant.camera(name, "--confirm-timeout", "60", "--resend-after", "1"))
               for name in CAMERAS]
    # All 80 acknowledged by the broker while the matcher is down; most are dropped.
    wait_until(lambda: "Outgoing messages are being dropped for client matcher1"
               in plant.broker.process.log_path.read_text(), 30, "the broker to drop")
    matcher = plant.start(plant.matcher(database, "--until-cameras-offline", "--idle-exit",
                                        "40"))
    for camera in cameras:
        code, out, err = finish(camera)
        report = json.loads(out)
        assert code == 0, err
        assert report["confirmed_all"] and report["unconfirmed"] == 0
        assert report["resent"] > 0, "the dropped messages came back from the spool"
    code, out, err = finish(matcher)
    assert code == 0, err
    counters = assert_all_stored_once(database)
    assert counters["processed"] == TOTAL and counters.get("late", 0) == 0


# -- item 2 ----------------------------------------------------------------------------------


def test_item2_broker_killed_after_the_cameras_finished_loses_nothing(plant, tmp_path):
    """What the broker acknowledged is on its disk once a save begun after the
    acknowledgement has been written (Mosquitto begins one when more than ``autosave_s``
    whole seconds have passed since the last: every 1-2 s by default): kill -9 after that
    loses nothing. (Before it, see the next test.)"""
    plant = plant()
    database = tmp_path / "plane1.db"
    assert plant.run(plant.matcher(database, "--prepare")).returncode == 0
    cameras = [plant.start(plant.camera(name, "--confirm-timeout", "0")) for name in CAMERAS]
    for camera in cameras:
        code, out, err = finish(camera)
        assert code == 0 and json.loads(out)["flushed"], err
    # Every message was acknowledged before the cameras exited: a save that begins after
    # this count holds them all. The broker logs a save as it begins writing (to a new
    # file it then renames over the old one), and saves one at a time: once the save after
    # that one has begun, the first is complete on disk. (Killed at its log line, the
    # broker lost everything: the restart read the previous file.)
    saved = broker_saves(plant)
    wait_until(lambda: broker_saves(plant) >= saved + 2, 30, "the broker's next save")
    plant.broker.process.kill()
    plant.broker.start()
    code, out, err = finish(plant.start(plant.matcher(database, "--until-cameras-offline",
                                                      "--idle-exit", "20")))
    assert code == 0, err
    assert_all_stored_once(database)


def test_item2_broker_killed_before_it_saved_loses_nothing(plant, tmp_path):
    """Killed within its save interval the broker loses the newest messages; the cameras,
    still holding them, send them again."""
    plant = plant(autosave_s=3600)  # the broker saves nothing before the kill
    database = tmp_path / "plane1.db"
    assert plant.run(plant.matcher(database, "--prepare")).returncode == 0
    cameras = [plant.start(plant.camera(name, "--confirm-timeout", "60", "--resend-after", "1"))
               for name in CAMERAS]
    wait_until(lambda: all(spool_rows(tmp_path / f"{name}.spool", state=2) == PER_CAMERA
                           for name in CAMERAS), 60, "the broker to acknowledge everything")
    plant.broker.process.kill()
    plant.broker.start()
    matcher = plant.start(plant.matcher(database, "--until-cameras-offline", "--idle-exit",
                                        "40"))
    for camera in cameras:
        code, out, err = finish(camera)
        assert code == 0 and json.loads(out)["confirmed_all"], err
    code, out, err = finish(matcher)
    assert code == 0, err
    assert_all_stored_once(database)


# -- item 3 ----------------------------------------------------------------------------------


def test_item3_cameras_before_the_first_matcher_lose_nothing(plant, tmp_path):
    """No matcher has ever subscribed: the broker drops everything. A camera says so (exit 3,
    nothing claimed), keeps its messages, and sends them when a matcher appears."""
    plant = plant()
    database = tmp_path / "plane1.db"
    early = plant.run(plant.camera("CVLab1", "--confirm-timeout", "1"))
    assert early.returncode == 3, early.stderr
    summary = json.loads(early.stdout)
    assert not summary["confirmed_all"] and summary["unconfirmed"] == PER_CAMERA
    assert spool_rows(tmp_path / "CVLab1.spool") == PER_CAMERA
    plain = plant.run([item for item in plant.camera("CVLab2", "--confirm-timeout", "1")
                       if item != "--json"])
    assert plain.returncode == 3
    assert "not yet confirmed by a matcher" in plain.stdout and "all confirmed" not in plain.stdout
    cameras = [plant.start(plant.camera(name, "--confirm-timeout", "60")) for name in CAMERAS]
    # Both published again and the broker acknowledged (and dropped) everything.
    wait_until(lambda: all(spool_rows(tmp_path / f"{name}.spool", state=2) == PER_CAMERA
                           for name in CAMERAS), 60, "the broker to acknowledge everything")
    matcher = plant.start(plant.matcher(database, "--until-cameras-offline", "--idle-exit",
                                        "40"))
    for camera in cameras:
        code, out, err = finish(camera)
        report = json.loads(out)
        assert code == 0 and report["confirmed_all"], err
    code, out, err = finish(matcher)
    assert code == 0, err
    assert_all_stored_once(database)


def test_item3_a_camera_never_claims_what_the_broker_refused(plant, tmp_path):
    """Wrong credentials for the topic: every publish refused by the ACL; exit 1, one
    sentence, nothing claimed (it used to print "all acknowledged")."""
    plant = plant()
    command = plant.camera("CVLab1", "--confirm-timeout", "0")
    command[command.index("--username") + 1] = "CVLab2"
    command[command.index("--password-file") + 1] = str(
        plant.broker.files.password_files["CVLab2"])
    result = plant.run(command)
    assert result.returncode == 1
    report = json.loads(result.stdout)
    assert report["refused_by_broker"] >= 1 and not report["flushed"]
    assert "Not authorized" in one_sentence(result.stderr)


# -- item 4 ----------------------------------------------------------------------------------


def test_item4_a_long_broker_outage_is_spooled_to_disk(plant, tmp_path):
    """The broker is away: the camera says so within seconds, spools to disk, survives its
    own SIGKILL, and its next start delivers everything; a full spool drops the oldest,
    counted and logged."""
    plant = plant()
    database = tmp_path / "plane1.db"
    assert plant.run(plant.matcher(database, "--prepare")).returncode == 0
    plant.broker.stop()
    camera = plant.start(plant.camera("CVLab1", "--flush-timeout", "600"))
    started = time.monotonic()
    wait_until(lambda: spool_rows(tmp_path / "CVLab1.spool") == PER_CAMERA, 30, "a full spool")
    camera.send_signal(signal.SIGKILL)
    _, err = camera.communicate()
    assert "cannot reach the MQTT broker" in err and "Connection refused" in err, err
    assert time.monotonic() - started < 30
    # A small spool: its policy when full (drop the oldest, count, say so).
    small = plant.run(plant.camera("CVLab2", "--flush-timeout", "1", "--spool-max-mb", "0.02"))
    assert small.returncode == 3
    report = json.loads(small.stdout)
    kept = spool_rows(tmp_path / "CVLab2.spool")
    assert report["dropped_from_spool"] == PER_CAMERA - kept > 0
    assert "is full" in small.stderr and "dropped the" in small.stderr
    plant.broker.start()
    matcher = plant.start(plant.matcher(database, "--until-cameras-offline", "--idle-exit",
                                        "30"))
    resumed = [plant.start(plant.camera(name, "--confirm-timeout", "60", replay=False))
               for name in CAMERAS]
    for camera in resumed:
        code, out, err = finish(camera)
        report = json.loads(out)
        assert code == 0 and report["confirmed_all"] and report["messages"] == 0, err
    code, out, err = finish(matcher)
    assert code == 0, err
    with RuntimeStore(database, read_only=True) as store:
        keys = {(m.message.camera_id, m.message.sequence) for m in store.messages()}
    assert {("CVLab1", sequence) for sequence in range(PER_CAMERA)} <= keys
    assert {key for key in keys if key[0] == "CVLab2"} == {
        ("CVLab2", sequence) for sequence in range(PER_CAMERA - kept, PER_CAMERA)}


# -- item 5 ----------------------------------------------------------------------------------


def test_item5_a_database_deleted_under_the_matcher_stops_it(plant, tmp_path):
    """The --db folder disappears mid-run: the matcher stops acknowledging and says why;
    a restart on an empty database is refused; restored, everything arrives once."""
    plant = plant()
    folder = tmp_path / "db"
    folder.mkdir()
    database = folder / "plane1.db"
    matcher = plant.start(plant.matcher(database))
    wait_until(lambda: database.exists(), 30, "the database")
    cameras = [plant.start(plant.camera(name, "--realtime", "--speed", "8",
                                        "--confirm-timeout", "90", "--resend-after", "1"))
               for name in CAMERAS]

    wait_until(lambda: counter(database, "accepted") >= 10, 60, "some messages")
    moved = tmp_path / "db-moved"
    folder.rename(moved)  # "deleted" (kept aside to restore it below)
    code, _, err = finish(matcher)
    assert code == 1
    assert "was deleted or replaced while the matcher was running" in one_sentence(err)
    folder.mkdir()
    again = plant.run(plant.matcher(database, "--idle-exit", "5"))
    assert again.returncode == 1
    assert "from another database" in one_sentence(again.stderr)
    restored = plant.start(plant.matcher(moved / "plane1.db", "--until-cameras-offline",
                                         "--idle-exit", "60"))
    for camera in cameras:
        code, out, err = finish(camera, timeout=120)
        assert code == 0 and json.loads(out)["confirmed_all"], err
    code, out, err = finish(restored)
    assert code == 0, err
    assert_all_stored_once(moved / "plane1.db")


# -- item 6 ----------------------------------------------------------------------------------


def test_item6_a_second_matcher_for_the_plane_is_refused(plant, tmp_path):
    """Same credentials, another database: the second matcher refuses in one sentence, the
    first keeps the plane, nothing lands in the second database."""
    plant = plant()
    first_db, second_db = tmp_path / "first.db", tmp_path / "second.db"
    since = time.time()
    first = plant.start(plant.matcher(first_db))  # runs until told to stop
    wait_matcher_online(plant, since)
    cameras = [plant.start(plant.camera(name, "--realtime", "--speed", "10",
                                        "--confirm-timeout", "60"))
               for name in CAMERAS]
    same_db = plant.run(plant.matcher(first_db, "--idle-exit", "30"), timeout=60)
    assert same_db.returncode == 1
    assert "is in use by another matcher" in one_sentence(same_db.stderr)
    second = plant.run(plant.matcher(second_db, "--idle-exit", "30"), timeout=60)
    assert second.returncode == 1
    assert "is already served by matcher matcher1" in one_sentence(second.stderr)
    assert first.poll() is None, "the first matcher must keep the plane"
    for camera in cameras:
        code, out, err = finish(camera, timeout=120)
        assert code == 0 and json.loads(out)["confirmed_all"], err
    first.send_signal(signal.SIGTERM)
    code, out, err = finish(first)
    assert code == 0, err
    assert_all_stored_once(first_db)
    with RuntimeStore(second_db, read_only=True) as store:
        assert store.messages() == [] and store.counters().get("received", 0) == 0


# -- item 10 ---------------------------------------------------------------------------------


def test_item10_sigterm_to_the_process_group_stops_cleanly_and_resumes(plant, tmp_path):
    """systemd stops the matcher with SIGTERM to its process group: exit 0, summary,
    --out-tracks; the restarted matcher finishes with --until-cameras-offline."""
    plant = plant()
    database = tmp_path / "plane1.db"
    tracks = tmp_path / "tracks.txt"
    matcher = plant.start(plant.matcher(database, "--out-tracks", str(tracks)),
                          start_new_session=True)
    wait_until(lambda: database.exists(), 30, "the matcher")
    cameras = [plant.start(plant.camera(name, "--realtime", "--speed", "10",
                                        "--confirm-timeout", "0"))
               for name in CAMERAS]

    wait_until(lambda: counter(database, "accepted") >= 10, 60, "some messages")
    os.killpg(matcher.pid, signal.SIGTERM)
    code, out, err = finish(matcher)
    assert code == 0, err
    assert "Traceback" not in err
    summary = json.loads(out)
    assert summary["stopped_by"] == "signal" and summary["out_tracks"] == str(tracks)
    assert tracks.exists()
    for camera in cameras:  # they finish while the matcher is down
        code, out, err = finish(camera)
        assert code == 0, err
    restarted = plant.run(plant.matcher(database, "--until-cameras-offline", "--idle-exit",
                                        "60", "--out-tracks", str(tracks)), timeout=90)
    assert restarted.returncode == 0, restarted.stderr
    assert json.loads(restarted.stdout)["stopped_by"] == "condition"
    assert_all_stored_once(database)
    assert len(tracks.read_text().splitlines()) > 0


def test_item10_clean_camera_shutdown_keeps_its_final_offline(plant, tmp_path):
    """A camera's clean end leaves its timestamped "offline" (not its last will) retained, so
    a matcher started afterwards knows the stream ended."""
    from cblrs.runtime.mqtt_transport import MqttTransport
    from cblrs.runtime.wire import decode_status

    plant = plant()
    code = plant.run(plant.camera("CVLab1", "--confirm-timeout", "0")).returncode
    assert code == 0
    seen: list = []
    viewer = MqttTransport("viewer", plant.broker.settings("viewer"), persistent=False)
    viewer.subscribe("cblrs/1/CVLab1/status",
                     lambda delivery: (seen.append(decode_status(delivery.payload)),
                                       delivery.ack()))
    viewer.connect()
    wait_until(lambda: seen, 10, "the retained status")
    viewer.close()
    assert seen[0].state == "offline" and seen[0].timestamp is not None
    shutil.rmtree(tmp_path / "unused", ignore_errors=True)


# -- item 9 ----------------------------------------------------------------------------------


def test_item9_matcher_login_mistakes_are_one_sentence(plant, tmp_path):
    """A wrong password, or a camera's credentials: exit 1 with one sentence, before the
    tracker process starts and before anything is acknowledged (no traceback)."""
    plant = plant()
    wrong = tmp_path / "wrong.password"
    wrong.write_text("not the password\n")
    command = plant.matcher(tmp_path / "a.db")
    command[command.index("--password-file") + 1] = str(wrong)
    result = plant.run(command)
    assert result.returncode == 1
    assert "refused the connection" in one_sentence(result.stderr)
    as_camera = plant.run(plant.matcher(tmp_path / "b.db", "--idle-exit", "5", user="CVLab1"))
    assert as_camera.returncode == 1
    sentence = one_sentence(as_camera.stderr)
    assert "refused this matcher's lease message" in sentence
    assert "log in with a matcher's credentials" in sentence
    with RuntimeStore(tmp_path / "b.db", read_only=True) as store:
        assert store.counters().get("received", 0) == 0


# -- item 12 ---------------------------------------------------------------------------------


def test_item12_logs_have_times_lifecycle_lines_and_rate_limited_rejections(plant, tmp_path):
    """INFO by default: connection, cameras online/offline, one line per rejection reason
    per 10 s (50 rejections give one line); -v adds cblrs debug lines, -vv paho's packets."""
    import re

    from cblrs.runtime.mqtt_transport import MqttTransport
    from cblrs.runtime.topics import detections_topic, status_topic
    from cblrs.runtime.wire import encode_status

    plant = plant()
    database = tmp_path / "plane1.db"
    since = time.time()
    matcher = plant.start(plant.matcher(database, "--until-cameras-offline", "--idle-exit",
                                        "60"))
    wait_matcher_online(plant, since)
    # CVLab1 sends only garbage, between its own "online" and final "offline"; the matcher
    # stops once CVLab2 has finished too.
    sender = MqttTransport("CVLab1", plant.broker.settings("CVLab1"), persistent=False)
    sender.connect()
    sender.publish(status_topic(1, "CVLab1"), encode_status(
        "CVLab1", "online", role="camera", timestamp=time.time()), retain=True)
    for _ in range(50):
        sender.publish(detections_topic(1, "CVLab1"), b"{not json")
    sender.publish(status_topic(1, "CVLab1"), encode_status(
        "CVLab1", "offline", role="camera", timestamp=time.time()), retain=True)
    assert sender.flush(10)
    sender.close()
    camera = plant.run(plant.camera("CVLab2", "--confirm-timeout", "5"))
    assert camera.returncode == 0, camera.stderr
    code, out, err = finish(matcher)
    assert code == 0, err
    stamp = r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3} (INFO|WARNING|ERROR) cblrs\."
    lines = [line for line in err.splitlines() if " cblrs." in line]
    assert lines and all(re.match(stamp, line) for line in lines), lines[:3]
    assert any("matcher1: connected to" in line for line in lines)
    assert any("camera CVLab2 is online" in line for line in lines)
    assert any("camera CVLab2 is offline" in line for line in lines)
    rejections = [line for line in lines if "(malformed_json)" in line]
    assert len(rejections) == 1, rejections
    assert json.loads(out)["rejected_by_reason"] == {"malformed_json": 50}
    assert "connected to" in camera.stderr and " DEBUG " not in camera.stderr
    verbose = plant.run([*plant.camera("CVLab2", "--confirm-timeout", "0")[:3], "-v",
                         *plant.camera("CVLab2", "--confirm-timeout", "0")[3:]])
    assert " DEBUG cblrs." in verbose.stderr and "Sending PUBLISH" not in verbose.stderr
    packets = plant.run([*plant.camera("CVLab2", "--confirm-timeout", "0")[:3], "-vv",
                         *plant.camera("CVLab2", "--confirm-timeout", "0")[3:]])
    assert "Sending PUBLISH" in packets.stderr
