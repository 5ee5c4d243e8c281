"""End to end: seven camera nodes replay WILDTRACK through a broker into one matcher service.

The stored tracks must equal those of the in-process reference run (``track_scene`` on the
same messages with the same matcher settings), row for row, and so score the same HOTA.
Runs on both transports: the in-process broker and a real Mosquitto on a loopback port.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from waiting import wait_until

from cblrs.datasets import load_scene
from cblrs.detections import Tracks
from cblrs.evaluation import evaluate
from cblrs.matching import make_matcher
from cblrs.pipeline import render_scene_references, scene_planes, track_scene
from cblrs.reference import ReferenceImage
from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.protocol import Will
from cblrs.runtime.transport.topics import tracks_topic
from cblrs.runtime.wire import decode_tracks

PLANE = 1
MATCHER = "fusion"


@pytest.fixture(scope="module")
def replay_case(wildtrack_root, tmp_path_factory):
    """The scene, reference PNGs read back from disk, the epoch and the reference run."""
    scene = load_scene(wildtrack_root)
    folder = tmp_path_factory.mktemp("references")
    references = []
    for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=True):
        path = reference.save(folder / f"{camera.name}.png")
        references.append(ReferenceImage.load(path, expected_size=camera.image_size))
    # Replayed capture times are epoch + scene time; the reference run sees the same times.
    epoch = float(int(time.time()) - 3600)
    shifted = replace(scene, timestamps=scene.timestamps + epoch)
    planes = scene_planes(scene)
    expected = track_scene(
        shifted, matcher=make_matcher(MATCHER, planes, scene.camera_names), references=references
    )
    return scene, references, epoch, expected.tracks


def replay(scene, references, epoch, make_transport, store, window_s=5.0, timeout=60.0,
           matcher_name=MATCHER):
    """Run the service and one camera node per scene camera (threads).

    Returns the service stats, the camera reports and the track updates a viewer received.
    """
    names = scene.camera_names
    updates = []
    viewer = make_transport("viewer")
    viewer.subscribe(
        tracks_topic(PLANE), lambda delivery: (updates.append(delivery.payload), delivery.ack())
    )
    viewer.connect()
    matcher = make_matcher(matcher_name, scene_planes(scene), names)
    if hasattr(matcher, "set_views"):
        matcher.set_views(references)  # as `cblrs matcher` does from its references
    service = MatcherService(
        make_transport("matcher"), store, matcher, PLANE, names, window_s=window_s
    )
    service.start()
    reports = {}

    def camera(index: int) -> None:
        name = names[index]
        will = Will(*camera_last_will(PLANE, name))
        transport = make_transport(name, persistent=False, will=will)
        node = CameraNode(transport, PLANE, name, references[index], epoch=epoch)
        reports[name] = node.run(scene_source(scene, index))
        transport.close()

    threads = [threading.Thread(target=camera, args=(index,)) for index in range(len(names))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout)
    assert all(not thread.is_alive() for thread in threads), "a camera node hung"
    wait_until(
        lambda: service.cameras_done() and service.drained(), timeout, "the matcher to finish"
    )
    service.close(flush=True)
    stats = service.stats()
    wait_until(lambda: len(updates) == stats["groups"], timeout, "every track update")
    return stats, reports, [decode_tracks(payload) for payload in updates]


def test_replay_through_broker_equals_in_process_run(replay_case, make_transport, tmp_path):
    scene, references, epoch, expected = replay_case
    with RuntimeStore(tmp_path / "matcher.db") as store:
        stats, reports, updates = replay(scene, references, epoch, make_transport, store)
        tracks = store.tracks()
        inbox = store.status_counts()
    messages = len(scene.frames) * len(scene.cameras)
    assert sum(report.messages for report in reports.values()) == messages
    assert all(report.flushed for report in reports.values())
    assert stats["received"] == messages
    assert stats["processed"] == messages
    assert (stats["rejected"], stats["duplicates"], stats["late"]) == (0, 0, 0)
    assert stats["groups"] == len(scene.frames)
    assert inbox == {"processed": messages}
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)
    np.testing.assert_array_equal(tracks.camera_id, expected.camera_id)
    assert stats["tracks"] == len(expected) > 0
    assert [update.sequence for update in updates] == list(range(1, len(scene.frames) + 1))
    published = Tracks.concatenate([update.tracks for update in updates])
    np.testing.assert_array_equal(published.track_id, expected.track_id)
    assert updates[0].cameras == tuple(scene.camera_names)
    got = evaluate(scene.ground_truth, tracks)
    want = evaluate(scene.ground_truth, expected)
    assert got.HOTA == pytest.approx(want.HOTA, abs=1e-9)
    assert got.HOTA > 50.0


def test_paper_matcher_runs_as_a_service(replay_case, tmp_path):
    """The paper's matcher behind the same service gives its in-process tracks too."""
    scene, references, epoch, _ = replay_case
    broker = InProcessBroker()

    def make_transport(name, persistent=True, will=None):
        return InProcessTransport(broker, name, persistent=persistent, will=will)

    shifted = replace(scene, timestamps=scene.timestamps + epoch)
    expected = track_scene(
        shifted, matcher=make_matcher("paper", scene_planes(scene), scene.camera_names),
        references=references,
    ).tracks
    with RuntimeStore(tmp_path / "paper.db") as store:
        stats, _, _ = replay(
            scene, references, epoch, make_transport, store, matcher_name="paper"
        )
        tracks = store.tracks()
    assert stats["late"] == 0
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)
