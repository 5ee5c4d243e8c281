"""Broker security with the configuration of ``cblrs broker-config``, on a real Mosquitto."""

from __future__ import annotations

import os
import stat
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
from test_runtime_transport import Collector  # tests/runtime is on sys.path (rootdir-relative)

from cblrs.runtime.broker.mosquitto_config import (
    BrokerError,
    MosquittoProcess,
    free_port,
    write_broker_config,
)
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.protocol import TransportError
from cblrs.runtime.transport.topics import detections_topic, status_topic, tracks_topic

pytestmark = pytest.mark.mqtt

WAIT = 5.0


def connect(broker, user, client_id=None, **options) -> MqttTransport:
    # Clean sessions: the broker keys sessions by user name, and tests must not inherit
    # messages queued for a user by an earlier test.
    transport = MqttTransport(client_id or user, broker.settings(user, **options), persistent=False)
    transport.connect()
    return transport


@pytest.fixture
def matcher(mosquitto_auth):
    transport = connect(mosquitto_auth, "matcher1")
    collector = Collector()
    transport.subscribe("cblrs/1/+/detections", collector)
    yield collector
    transport.close(timeout=1)


def test_anonymous_client_is_refused(mosquitto_auth):
    transport = MqttTransport("anonymous", mosquitto_auth.settings(None))
    with pytest.raises(TransportError, match="refused the connection: Not authorized"):
        transport.connect()


def test_wrong_password_is_refused(mosquitto_auth):
    settings = replace(mosquitto_auth.settings("CVLab1"), password="not the password")
    transport = MqttTransport("CVLab1", settings)
    # Mosquitto 2.0 answers "Not authorized" rather than "Bad user name or password".
    with pytest.raises(
        TransportError, match=r"refused the connection: (Bad user name or password|Not authorized)"
    ):
        transport.connect()


def test_unknown_user_is_refused(mosquitto_auth):
    settings = replace(mosquitto_auth.settings("CVLab1"), username="CVLab9")
    with pytest.raises(TransportError, match="refused the connection"):
        MqttTransport("CVLab9", settings).connect()


def test_camera_publishes_only_on_its_own_topics(mosquitto_auth, matcher):
    camera = connect(mosquitto_auth, "CVLab1")
    camera.publish(detections_topic(1, "CVLab2"), b"spoofed")  # another camera's topic
    camera.publish(tracks_topic(1), b"fake tracks")
    camera.publish(detections_topic(1, "CVLab1"), b"genuine")  # its own: allowed
    assert camera.flush(WAIT)
    assert [delivery.payload for delivery in matcher.wait_for(1)] == [b"genuine"]
    assert matcher.settle(0.2) and matcher.payloads == [b"genuine"]
    assert camera.refused_publishes == 2  # Mosquitto answers "Not authorized" under MQTT 5
    camera.close()


def test_camera_cannot_read_detections_or_tracks(mosquitto_auth):
    spy = connect(mosquitto_auth, "CVLab1")
    collector = Collector()
    for topic_filter in ("cblrs/1/+/detections", "cblrs/#", "#", tracks_topic(1)):
        try:
            spy.subscribe(topic_filter, collector)
        except TransportError as error:  # refused outright is fine too
            assert "refused the subscription" in str(error)
    other = connect(mosquitto_auth, "CVLab2")
    other.publish(detections_topic(1, "CVLab2"), b"secret")
    other.publish(status_topic(1, "CVLab2"), b"online", retain=True)
    assert other.flush(WAIT)
    publisher = connect(mosquitto_auth, "matcher1")
    publisher.publish(tracks_topic(1), b"tracks")
    assert publisher.flush(WAIT)
    assert collector.settle(0.3) == []
    for transport in (spy, other, publisher):
        transport.close()


def test_matcher_cannot_inject_detections(mosquitto_auth, matcher):
    rogue = connect(mosquitto_auth, "matcher2")
    rogue.publish(detections_topic(1, "CVLab1"), b"injected")
    assert rogue.flush(WAIT)
    assert matcher.settle(0.2) == []
    assert rogue.refused_publishes == 1
    rogue.close()


def test_viewer_reads_tracks_but_not_detections(mosquitto_auth):
    viewer = connect(mosquitto_auth, "viewer")
    tracks, detections = Collector(), Collector()
    viewer.subscribe(tracks_topic(1), tracks)
    try:
        viewer.subscribe("cblrs/1/+/detections", detections)
    except TransportError:
        pass
    camera = connect(mosquitto_auth, "CVLab1")
    camera.publish(detections_topic(1, "CVLab1"), b"detections")
    matcher = connect(mosquitto_auth, "matcher1")
    matcher.publish(tracks_topic(1), b"tracks")
    assert tracks.wait_for(1) and tracks.payloads == [b"tracks"]
    assert detections.settle(0.2) == []
    for transport in (viewer, camera, matcher):
        transport.close()


def test_another_user_cannot_take_over_a_matchers_session(mosquitto_auth, matcher):
    # The camera claims the matcher's client id; the broker uses the user name instead.
    impostor = connect(mosquitto_auth, "CVLab1", client_id="matcher1")
    camera = connect(mosquitto_auth, "CVLab2")
    camera.publish(detections_topic(1, "CVLab2"), b"still delivered")
    assert [delivery.payload for delivery in matcher.wait_for(1)] == [b"still delivered"]
    impostor.close()
    camera.close()


def test_tls_round_trip_with_client_certificates(mosquitto_tls):
    matcher = connect(mosquitto_tls, "matcher1")
    collector = Collector()
    matcher.subscribe("cblrs/2/+/detections", collector)
    camera = connect(mosquitto_tls, "CVLab2")
    camera.publish(detections_topic(2, "CVLab2"), b"over TLS")
    assert [delivery.payload for delivery in collector.wait_for(1)] == [b"over TLS"]
    camera.close()
    matcher.close()


def test_plain_tcp_client_to_the_tls_port_fails(mosquitto_tls):
    settings = replace(
        mosquitto_tls.settings("CVLab1", connect_timeout_s=0.5),
        ca_file=None,
        cert_file=None,
        key_file=None,
    )
    with pytest.raises(TransportError, match="no answer from the MQTT broker"):
        MqttTransport("CVLab1", settings).connect()


def test_tls_client_without_a_certificate_fails(mosquitto_tls):
    settings = replace(
        mosquitto_tls.settings("CVLab1", connect_timeout_s=0.5), cert_file=None, key_file=None
    )
    with pytest.raises(TransportError, match="no answer from the MQTT broker"):
        MqttTransport("CVLab1", settings).connect()


def test_acl_and_credentials_files(mosquitto_auth):
    files = mosquitto_auth.files
    acl = files.acl_file.read_text()
    assert (
        "user CVLab1\ntopic write cblrs/+/CVLab1/detections\ntopic write cblrs/+/CVLab1/status\n"
        "topic read cblrs/+/CVLab1/stored\ntopic read cblrs/+/matchers/+/status\n"
        in acl
    )
    assert "topic read cblrs/1/+/detections" in acl and "topic read cblrs/2/+/detections" in acl
    assert "topic write cblrs/1/tracks" in acl
    assert "topic write cblrs/1/alerts" in acl and "topic read cblrs/+/alerts" in acl
    credentials = files.credentials()
    assert set(credentials) == {"CVLab1", "CVLab2", "matcher1", "matcher2", "viewer"}
    assert files.roles["CVLab1"] == "camera" and files.roles["viewer"] == "viewer"
    assert len(set(credentials.values())) == 5
    assert stat.S_IMODE(os.stat(files.password_file).st_mode) == 0o600
    # The ACL (every login and what it may do), the configuration and the broker's log
    # (logins, addresses, refusals) are the owner's alone too.
    for path in (files.acl_file, files.config, mosquitto_auth.process.log_path):
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o600, path
    # No clear password anywhere in the broker's folder: only hashes.
    for path in files.directory.rglob("*"):
        if path.is_file() and path.suffix != ".db":
            text = path.read_bytes()
            for password in credentials.values():
                assert password.encode() not in text, path
    # Each client's secrets sit in a 0700 folder of its own, outside the broker's.
    for user, client in files.clients.items():
        assert files.directory not in client.directory.parents
        assert stat.S_IMODE(os.stat(client.directory).st_mode) == 0o700
        assert stat.S_IMODE(os.stat(client.password_file).st_mode) == 0o600
        assert [path.name for path in client.directory.iterdir()] == [f"{user}.password"]
    config = files.config.read_text()
    assert "allow_anonymous false" in config and "persistence_location" in config


@pytest.mark.parametrize(
    ("cameras", "matchers", "options", "message"),
    [
        (["bad/name"], ["m"], {}, "camera id 'bad/name' is not usable"),
        (["c"], ["c"], {}, "must be distinct"),
        ([], [], {}, "at least one camera or matcher"),
        (["c"], ["m"], {"plane_ids": [0]}, "plane ids must be 1..65535"),
        (["c"], ["m"], {"port": 0}, "port must be 1..65535"),
    ],
)
def test_write_broker_config_refuses(tmp_path, cameras, matchers, options, message):
    options = {"port": 1883, **options}
    with pytest.raises(Exception, match=message) as caught:
        write_broker_config(tmp_path, cameras, matchers, **options)
    assert isinstance(caught.value, BrokerError) or "not usable" in message


def test_certificates_are_valid_for_a_year(mosquitto_tls):
    from cryptography import x509

    server = x509.load_pem_x509_certificate(
        (mosquitto_tls.files.ca_file.parent / "server.crt").read_bytes()
    )
    lifetime = server.not_valid_after_utc - server.not_valid_before_utc
    assert 364 <= lifetime.days <= 366
    names = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "localhost" in names.get_values_for_type(x509.DNSName)
    assert time.time() < server.not_valid_after_utc.timestamp()


def test_broker_config_command_writes_a_working_configuration(tmp_path, capsys):
    from broker_user import RUN_AS

    from cblrs.cli.main import main
    from cblrs.runtime.broker.mosquitto_config import MosquittoProcess, free_port
    from cblrs.runtime.transport.mqtt_transport import MqttSettings

    port = free_port()
    out = tmp_path / "broker"
    arguments = ["broker-config", "--out", str(out), "--cameras", "CVLab1,CVLab2"]
    if RUN_AS:
        arguments += ["--run-as", RUN_AS]
    assert main([*arguments, "--matchers", "matcher1", "--planes", "1,2", "--port", str(port)]) == 0
    printed = capsys.readouterr().out
    assert f"mosquitto -c {out / 'mosquitto.conf'}" in printed
    clients = tmp_path / "broker-clients"
    assert f"--password-file {clients / 'CVLab1' / 'CVLab1.password'}" in printed
    # Running it again would silently replace every password: refused without --force.
    assert main([*arguments, "--port", str(port)]) == 2
    assert "use --force" in capsys.readouterr().err

    password = (clients / "matcher1" / "matcher1.password").read_text().strip()
    assert stat.S_IMODE(os.stat(clients / "matcher1" / "matcher1.password").st_mode) == 0o600
    with MosquittoProcess(out / "mosquitto.conf", port):
        settings = MqttSettings(port=port, username="matcher1", password=password)
        matcher = MqttTransport("matcher1", settings, persistent=False)
        matcher.connect()
        collector = Collector()
        matcher.subscribe("cblrs/2/+/detections", collector)
        camera_password = (clients / "CVLab2" / "CVLab2.password").read_text().strip()
        camera = MqttTransport(
            "CVLab2", replace(settings, username="CVLab2", password=camera_password)
        )
        camera.connect()
        camera.publish(detections_topic(2, "CVLab2"), b"hello")
        assert [delivery.payload for delivery in collector.wait_for(1)] == [b"hello"]
        camera.close()
        matcher.close()


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--cameras", ""], "--cameras needs at least one camera id"),
        (["--cameras", "a,a"], "--cameras lists a name twice"),
        (["--cameras", "a", "--planes", "one"], "--planes 'one' must be integers"),
        (["--cameras", "a", "--planes", "0"], "plane ids must be 1..65535"),
        (["--cameras", "a/b"], "camera id 'a/b' is not usable in MQTT topics"),
    ],
)
def test_broker_config_command_errors(tmp_path, capsys, arguments, message):
    from cblrs.cli.main import main

    assert main(["broker-config", "--out", str(tmp_path), *arguments]) != 0
    error = capsys.readouterr().err
    assert message in error and "Traceback" not in error


# -- issue 10, item 14: identity, keys, passwords, privileges, sizes -----------------------


def test_a_client_certificate_is_its_users_identity(mosquitto_tls):
    # CVLab1's certificate with CVLab2's login: the broker takes the certificate's name.
    cert, key = mosquitto_tls.files.client_certificates["CVLab1"]
    settings = replace(mosquitto_tls.settings("CVLab2"), cert_file=cert, key_file=key)
    matcher = connect(mosquitto_tls, "matcher1")
    collector = Collector()
    matcher.subscribe("cblrs/1/+/detections", collector)
    mixed = MqttTransport("CVLab2", settings, persistent=False)
    mixed.connect()
    answers: list[int] = []
    mixed.publish(detections_topic(1, "CVLab2"), b"as CVLab2", on_result=answers.append)
    mixed.publish(detections_topic(1, "CVLab1"), b"as CVLab1", on_result=answers.append)
    assert mixed.flush(WAIT)
    assert answers == [0x87, 0], "publishing as CVLab2 with CVLab1's certificate must fail"
    assert [delivery.payload for delivery in collector.wait_for(1)] == [b"as CVLab1"]
    mixed.close()
    matcher.close()


def test_the_ca_key_stays_out_of_the_broker_folder(mosquitto_tls):
    files = mosquitto_tls.files
    assert files.ca_key_file is not None and files.ca_key_file.is_file()
    assert files.directory not in files.ca_key_file.parents
    assert not list(files.directory.rglob("ca.key"))
    assert stat.S_IMODE(os.stat(files.ca_key_file).st_mode) == 0o600
    assert stat.S_IMODE(os.stat(files.ca_key_file.parent).st_mode) == 0o700
    for line in files.config.read_text().splitlines():
        assert str(files.ca_key_file) not in line


def test_passwords_are_hashed_without_any_command_line(tmp_path, monkeypatch):
    import subprocess

    def refuse(*args, **kwargs):
        raise AssertionError(f"no process may be started to hash passwords: {args[0]}")

    monkeypatch.setattr(subprocess, "run", refuse)
    monkeypatch.setattr(subprocess, "Popen", refuse)
    files = write_broker_config(tmp_path / "b", ["CVLab1"], ["matcher1"], port=1883,
                                passwords={"CVLab1": "pa55word"}, run_as=_run_as())
    line = next(item for item in files.password_file.read_text().splitlines()
                if item.startswith("CVLab1:"))
    kind, iterations, salt, digest = line.split(":", 1)[1].split("$")[1:]
    assert (kind, iterations) == ("7", "101")
    import base64
    import hashlib

    expected = hashlib.pbkdf2_hmac("sha512", b"pa55word", base64.b64decode(salt), 101)
    assert base64.b64decode(digest) == expected


def test_a_broker_configured_as_root_does_not_run_as_root(tmp_path):
    if os.geteuid() != 0:
        config = write_broker_config(tmp_path / "b", ["c"], ["m"], port=1883).config.read_text()
        assert "\nuser " not in config  # not root: mosquitto keeps the user that starts it
        return
    import pwd
    import shutil
    import tempfile

    # A folder the service user cannot enter is refused in one sentence, before writing.
    with pytest.raises(BrokerError, match=r"runs as user mosquitto, which cannot enter "):
        write_broker_config(tmp_path / "b", ["c"], ["m"], port=1883)
    folder = Path(tempfile.mkdtemp(prefix="cblrs-broker-"))
    try:
        os.chmod(folder, 0o755)
        files = write_broker_config(folder / "b", ["c"], ["m"], port=free_port())
        config = files.config.read_text()
        assert "\nuser mosquitto\n" in config and "user root" not in config
        service = pwd.getpwnam("mosquitto").pw_uid
        for path in (files.directory, files.config, files.password_file, files.acl_file,
                     files.persistence_directory):
            assert path.stat().st_uid == service, path
        for client in files.clients.values():
            assert client.directory.stat().st_uid == 0, f"{client} must stay with its owner"
        with MosquittoProcess.from_files(files) as broker:  # it reads them as that user
            assert broker.running
    finally:
        shutil.rmtree(folder)


def test_oversized_messages_never_reach_the_broker(mosquitto_auth, matcher):
    camera = connect(mosquitto_auth, "CVLab1")
    answers: list[int] = []
    camera.publish(detections_topic(1, "CVLab1"), b"x" * (2 * 1024 * 1024),
                   on_result=answers.append)
    camera.publish(detections_topic(1, "CVLab1"), b"small", on_result=answers.append)
    assert camera.flush(WAIT)
    assert answers == [0x95, 0]
    assert camera.connected and camera.disconnections == 0
    assert [delivery.payload for delivery in matcher.wait_for(1)] == [b"small"]
    assert matcher.settle(0.2) and matcher.payloads == [b"small"]
    camera.close()


def test_the_broker_itself_refuses_oversized_packets(mosquitto_auth, matcher):
    # A client that does not check (a plain paho client) is disconnected; nothing arrives.
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    files = mosquitto_auth.files
    client = mqtt.Client(callback_api_version=CallbackAPIVersion.VERSION2, client_id="CVLab2",
                         protocol=mqtt.MQTTv5)
    client.username_pw_set("CVLab2", files.credentials()["CVLab2"])
    disconnected = threading.Event()
    client.on_disconnect = lambda *args: disconnected.set()
    client.connect("127.0.0.1", files.port)
    client.loop_start()
    try:
        client.publish(detections_topic(1, "CVLab2"), b"x" * (2 * 1024 * 1024), qos=1)
        assert disconnected.wait(WAIT)
    finally:
        client.loop_stop()
    assert matcher.settle(0.2) == []


def _run_as():
    from broker_user import RUN_AS

    return RUN_AS


# -- issue 18, item 5: one login, one client ------------------------------------------------


def test_a_second_client_with_the_same_login_is_logged_and_counted(mosquitto_auth, caplog):
    """The broker uses the login as the client id, so nobody can pick another user's session;
    the price is that a login shared by two clients is one session they take from each other:
    the client that loses it says so at ERROR and counts it (the matcher's /metrics shows
    cblrs_session_takeovers)."""
    from waiting import wait_until

    first = connect(mosquitto_auth, "matcher1")
    intruder = MqttTransport("anything", mosquitto_auth.settings("matcher1"), persistent=False)
    with caplog.at_level("ERROR", logger="cblrs.runtime.transport.mqtt_transport"):
        intruder.connect()
        # Two clients with one login take the session from each other until one leaves;
        # Mosquitto 2.0.11 closes the older one without MQTT 5's reason 0x8E, so a
        # connection closed within seconds of being accepted is what both see.
        wait_until(lambda: first.takeovers + intruder.takeovers >= 2, 3 * WAIT,
                   "the take-overs to be noticed")
        intruder.close()
    assert "another client logged in as matcher1 and took over this session" in caplog.text
    wait_until(lambda: first.connected, WAIT, "the first client to keep the session")
    first.close()


def test_each_dashboard_gets_its_own_viewer_login(tmp_path):
    files = write_broker_config(tmp_path / "b", ["CVLab1"], {"matcher1": [1], "matcher2": [2]},
                                port=1883, viewers=["wall", "desk"], run_as=_run_as())
    assert files.roles == {"CVLab1": "camera", "matcher1": "matcher", "matcher2": "matcher",
                           "wall": "viewer", "desk": "viewer"}
    acl = files.acl_file.read_text()
    assert "user wall\ntopic read cblrs/+/tracks" in acl and "user desk\n" in acl
    matcher1 = acl[acl.index("user matcher1"):acl.index("user matcher2")]
    assert "cblrs/1/+/detections" in matcher1 and "cblrs/2/" not in matcher1
