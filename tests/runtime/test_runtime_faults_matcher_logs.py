"""Fault tests of issue 10, the matcher's side, items 9 and 12: login mistakes in one sentence,
logs with times, lifecycle lines and rate-limited rejections (real Mosquitto and ``cblrs``
processes; the plant is in fault_plant.py, items 5-10 in test_runtime_faults_matcher.py).
"""

from __future__ import annotations

import json
import time

import pytest
from fault_plant import finish, one_sentence, wait_matcher_online

from cblrs.runtime.matcher.store import RuntimeStore

pytestmark = pytest.mark.mqtt


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
