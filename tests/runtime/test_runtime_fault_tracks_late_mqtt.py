"""Late messages are tracked (issue 20, item 1) with real `cblrs camera` / `cblrs matcher`
processes on Mosquitto: a restarted matcher, and a killed broker whose messages come back
late from the cameras' spools. Tracks equal the undisturbed run's (fault_tracks.py).
"""

from __future__ import annotations

import json
import subprocess

import pytest
from fault_tracks import (
    CAMERAS,
    ENVIRONMENT,
    FIRST,
    LAST,
    PER_CAMERA,
    TOTAL,
    assert_undisturbed,
    camera,
    counter,
    finish,
    make_case,
    matcher,
    start,
)
from waiting import wait_until


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory) -> dict:
    return make_case(wildtrack_root, tmp_path_factory)


@pytest.mark.mqtt
def test_item1_late_messages_for_a_restarted_matcher_are_tracked(case, start_mosquitto,
                                                                 tmp_path):
    """CVLab2 sends its first 20 frames and goes offline, CVLab1 sends all 40; the matcher
    tracks them and stops (every camera offline). Restarted on the same --db, it gets
    CVLab2's other 20 frames (a second run of the camera, numbered on): their times were
    released before the restart, so they are late. They are re-tracked from a snapshot
    before them, and the tracks are the undisturbed run's."""
    broker = start_mosquitto(cameras=CAMERAS, matchers=("matcher1",), plane_ids=(1,))

    def login(user: str) -> list[str]:
        return ["--broker", f"127.0.0.1:{broker.port}", "--username", user,
                "--password-file", str(broker.files.password_files[user])]

    database = tmp_path / "plane1.db"
    prepared = subprocess.run(matcher(case, database, login("matcher1"), "--prepare"),
                              capture_output=True, text=True, env=ENVIRONMENT, timeout=120)
    assert prepared.returncode == 0, prepared.stderr
    half = PER_CAMERA // 2
    runs = [("CVLab2", f"{FIRST}:95", "CVLab2.spool", "0"),
            ("CVLab1", f"{FIRST}:{LAST}", None, "0"),
            ("CVLab2", f"100:{LAST}", "CVLab2-again.spool", str(half))]
    summaries = []
    for restart in (False, True):
        served = start(matcher(case, database, login("matcher1"), "--until-cameras-offline",
                               "--idle-exit", "60"))
        cameras = [start(camera(case, tmp_path, name, login(name), "--confirm-timeout", "60",
                                "--first-sequence", first, frames=frames, spool=spool))
                   for name, frames, spool, first in (runs[2:] if restart else runs[:2])]
        for process in cameras:
            code, out, err = finish(process)
            assert code == 0 and json.loads(out)["confirmed_all"], err[-3000:]
        code, out, err = finish(served)
        assert code == 0, err[-3000:]
        summaries.append(json.loads(out))
    first, second = summaries
    assert first["late"] == 0 and first["processed"] == PER_CAMERA + half, first
    assert second["late"] == half and second["late_tracked"] == half, second
    assert second["retracks"] == 1 and second["processed"] == TOTAL, second
    assert 0 < second["retracked"] < TOTAL, "re-tracked from the empty tracker, not a snapshot"
    assert_undisturbed(database, case)


@pytest.mark.mqtt
def test_item1_spooled_messages_lost_with_a_killed_broker_are_tracked_late(
        case, start_mosquitto, tmp_path):
    """CVLab2 publishes everything with --confirm-timeout 0 and leaves; Mosquitto is killed
    before it saved them (they are lost; CVLab2's spool still holds them). With the broker
    back, the matcher tracks CVLab1 alone (CVLab2 silent for its 1 s window); CVLab2's next
    start re-sends its spool: all 40 messages late. They are re-tracked (from the empty
    tracker's snapshot) and the tracks are the undisturbed run's."""
    broker = start_mosquitto(cameras=CAMERAS, matchers=("matcher1",), plane_ids=(1,),
                             autosave_s=3600)

    def login(user: str) -> list[str]:
        return ["--broker", f"127.0.0.1:{broker.port}", "--username", user,
                "--password-file", str(broker.files.password_files[user])]

    database = tmp_path / "plane1.db"
    prepared = subprocess.run(matcher(case, database, login("matcher1"), "--prepare"),
                              capture_output=True, text=True, env=ENVIRONMENT, timeout=120)
    assert prepared.returncode == 0, prepared.stderr
    code, out, err = finish(start(camera(case, tmp_path, "CVLab2", login("CVLab2"),
                                         "--confirm-timeout", "0")))
    assert code == 0 and json.loads(out)["unconfirmed"] == PER_CAMERA, err[-3000:]
    broker.process.kill()
    broker.start()
    served = start(matcher(case, database, login("matcher1"), "--window", "1",
                           "--until-cameras-offline", "--idle-exit", "60"))
    code, out, err = finish(start(camera(case, tmp_path, "CVLab1", login("CVLab1"),
                                         "--confirm-timeout", "60")))
    assert code == 0 and json.loads(out)["confirmed_all"], err[-3000:]
    wait_until(lambda: counter(database, "processed") == PER_CAMERA, 60,
               "CVLab1's frames tracked without CVLab2")
    assert counter(database, "accepted") == PER_CAMERA, "CVLab2's messages were not lost"
    code, out, err = finish(start(camera(case, tmp_path, "CVLab2", login("CVLab2"),
                                         "--confirm-timeout", "60", replay=False)))
    assert code == 0 and json.loads(out)["confirmed_all"], err[-3000:]
    code, out, err = finish(served)
    assert code == 0, err[-3000:]
    summary = json.loads(out)
    assert summary["late"] == PER_CAMERA and summary["late_tracked"] == PER_CAMERA, summary
    assert summary["retracks"] >= 1 and summary["processed"] == TOTAL, summary
    assert_undisturbed(database, case)
