"""Fault tests of issue 10, the broker's side, items 3-4: cameras before the first matcher, a
publish the broker refused, a long broker outage spooled to disk (real Mosquitto, real
``cblrs camera`` / ``cblrs matcher`` processes; the plant is in fault_plant.py, items 1-2 in
test_runtime_faults.py). "What cblrs guarantees" in docs/services.md names the test behind
each of its lines.
"""

from __future__ import annotations

import json
import signal
import time

import pytest
from fault_plant import (
    CAMERAS,
    PER_CAMERA,
    assert_all_stored_once,
    finish,
    one_sentence,
    spool_rows,
)
from waiting import wait_until

from cblrs.runtime.matcher.store import RuntimeStore

pytestmark = pytest.mark.mqtt


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
