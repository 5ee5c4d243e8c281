"""Fault tests of issue 10, the matcher's side (items 5-12): a deleted database, a second
matcher, signals, login mistakes, logs — real Mosquitto and ``cblrs`` processes (the plant is
in fault_plant.py; items 1-4 are in test_runtime_faults.py). "What cblrs guarantees" in
docs/services.md names the test behind each of its lines.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time

import pytest
from fault_plant import (
    CAMERAS,
    assert_all_stored_once,
    counter,
    finish,
    one_sentence,
    wait_matcher_online,
)
from waiting import wait_until

from cblrs.runtime.matcher.store import RuntimeStore

pytestmark = pytest.mark.mqtt


def test_item5_a_database_deleted_under_the_matcher_stops_it(plant, tmp_path):
    """The --db folder disappears mid-run: the matcher stops acknowledging and says why;
    a restart on an empty database is refused; restored, everything arrives once."""
    plant = plant()
    folder = tmp_path / "db"
    folder.mkdir()
    database = folder / "plane1.db"
    matcher = plant.start(plant.matcher(database))
    wait_until(lambda: database.exists(), 120, "the database")  # a loaded machine starts slowly
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
    wait_until(lambda: database.exists(), 120, "the matcher")
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
    from cblrs.runtime.transport.mqtt_transport import MqttTransport
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
    wait_until(lambda: seen, 60, "the retained status")
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

    from cblrs.runtime.transport.mqtt_transport import MqttTransport
    from cblrs.runtime.transport.topics import detections_topic, status_topic
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
