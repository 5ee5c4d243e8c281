"""Fault tests of issue 10, the matcher's side (items 5-12): a deleted database, a second
matcher, signals — real Mosquitto and ``cblrs`` processes (the plant is in fault_plant.py;
items 1-4 are in test_runtime_faults.py and test_runtime_faults_outage.py, login mistakes and
logs, items 9 and 12, in test_runtime_faults_matcher_logs.py). "What cblrs guarantees" in
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
    assert "is already served by matcher matcher1" in one_sentence(second.stderr), second.stderr
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
