"""Unsynchronised cameras through the services: own clocks, frame rates, lost messages.

Camera nodes publish the simulated cameras' messages (each with its own clock offset and
jitter, frame rate and lost messages, or a clock two seconds off) through a broker — the
in-process one and a real Mosquitto — to one matcher service. Its stored tracks must equal
the in-process run on the same messages, row for row, however the cameras' messages
interleave on the way.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from waiting import wait_until

from cblrs.datasets import load_scene
from cblrs.datasets.clocks import ClockSimulation
from cblrs.datasets.presets import make_scene
from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.pipeline import camera_positions, render_scene_references, scene_planes, track_scene
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.protocol import Will
from cblrs.runtime.transport.topics import detections_topic
from cblrs.runtime.wire import encode_message

PLANE = 1


def fusion(scene):
    return make_matcher(
        "fusion", scene_planes(scene), scene.camera_names, camera_positions=camera_positions(scene)
    )


def replay(scene, references, clocks, make_transport, store, timeout=120.0):
    """Camera nodes (threads) publish the simulated cameras; returns the service's stats."""
    names = scene.camera_names
    matcher = fusion(scene)
    matcher.set_views(references)  # as `cblrs matcher` does from its references
    service = MatcherService(make_transport("matcher"), store, matcher, PLANE, names, window_s=5.0)
    service.start()

    def camera(index: int) -> None:
        name = names[index]
        transport = make_transport(
            name, persistent=False, will=Will(*camera_last_will(PLANE, name))
        )
        node = CameraNode(transport, PLANE, name, references[index], epoch=clocks.epoch_s)
        node.run(scene_source(scene, index, replace(clocks, epoch_s=0.0)))
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
    return service.stats()


@pytest.fixture(scope="module")
def wildtrack(wildtrack_root):
    scene = load_scene(wildtrack_root)
    return scene, render_scene_references(scene)


@pytest.fixture(scope="module")
def plaza():
    scene = make_scene("plaza", fps=30.0, duration_s=8.0)
    return scene, render_scene_references(scene)


EPOCH = float(int(time.time()) - 3600)
CASES = {
    "wildtrack ±50 ms": (
        "wildtrack",
        ClockSimulation(offset_s=0.05, jitter_s=0.003, drop=0.1, seed=1, epoch_s=EPOCH),
    ),
    "wildtrack one clock 2 s ahead": (
        "wildtrack",
        ClockSimulation(
            offset_s=0.02,
            jitter_s=0.003,
            drop=0.1,
            seed=2,
            clock_errors={"CVLab3": 2.0},
            epoch_s=EPOCH,
        ),
    ),
    "plaza 10 + 15 fps ±50 ms": (
        "plaza",
        ClockSimulation(
            offset_s=0.05, jitter_s=0.003, drop=0.1, camera_fps=(10.0, 15.0), seed=3, epoch_s=EPOCH
        ),
    ),
}


@pytest.fixture(scope="module")
def in_process_runs() -> dict:
    """Case -> the in-process run, tracked once for both transports (deterministic)."""
    return {}


@pytest.mark.parametrize("case", list(CASES))
def test_unsynchronised_replay_equals_the_in_process_run(
    case, request, make_transport, tmp_path, in_process_runs
):
    scene_name, clocks = CASES[case]
    scene, references = request.getfixturevalue(scene_name)
    if case not in in_process_runs:
        in_process_runs[case] = track_scene(
            scene, fusion(scene), references=references, clocks=clocks
        )
    expected = in_process_runs[case]
    with RuntimeStore(tmp_path / "matcher.db") as store:
        stats = replay(scene, references, clocks, make_transport, store)
        tracks = store.tracks()
    assert stats["late"] == 0 and stats["rejected"] == 0
    assert stats["processed"] == expected.message_count
    np.testing.assert_array_equal(tracks.frame, expected.tracks.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.tracks.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.tracks.world_xy)
    keys = set(zip(tracks.frame.tolist(), tracks.track_id.tolist(), strict=True))
    assert len(keys) == len(tracks) > 0  # one row per track and frame
    off = {name for name, report in stats["clocks"].items() if report["beyond_tolerance"]}
    assert off == ({"CVLab3"} if clocks.clock_errors else set())
    if clocks.clock_errors:
        assert stats["clocks"]["CVLab3"]["offset_s"] == pytest.approx(2.0, abs=0.06)


# -- release despite a dropped frame -----------------------------------------------------------


def _message(camera: str, sequence: int, timestamp: float) -> bytes:
    message = CameraMessage(
        camera,
        sequence,
        timestamp,
        sequence,
        np.array([[0.0, 0, 10, 10]]),
        np.array([0.9]),
        np.array([0]),
        np.array([[1000 + 100 * sequence, 2000, PLANE]]),
    )
    return encode_message(message, PLANE)


class _Groups:
    def __init__(self):
        self.groups: list[tuple[float, list[str]]] = []

    def on_group(self, timestamp, messages, tracks, wall_time):
        self.groups.append((timestamp, [message.camera_id for message in messages]))


@pytest.fixture
def service(tmp_path):
    broker = InProcessBroker()
    groups = _Groups()
    store = RuntimeStore(tmp_path / "matcher.db")
    matcher = make_matcher(
        "fusion", PlaneSet([PlaneSpec(PLANE, (0.0, 0.0), 20.0, 20.0)]), ["A", "B"]
    )
    running = MatcherService(
        InProcessTransport(broker, "matcher"),
        store,
        matcher,
        PLANE,
        ["A", "B"],
        window_s=3600.0,
        observer=groups,
    )
    running.start()
    publisher = InProcessTransport(broker, "publisher", persistent=False)
    publisher.connect()

    def publish(camera: str, sequence: int, timestamp: float) -> None:
        publisher.publish(detections_topic(PLANE, camera), _message(camera, sequence, timestamp))

    yield SimpleNamespace(service=running, store=store, groups=groups, publish=publish)
    running.close()
    store.close()


def test_service_releases_despite_a_dropped_frame(service):
    """Camera B loses its frame at 0.2 s. The service does not wait for it (the silence
    timeout here is an hour): B's next frame shows it has moved on."""
    now = time.time()
    for sequence in range(2):
        service.publish("A", sequence, now + 0.1 * sequence)
        service.publish("B", sequence, now + 0.1 * sequence + 0.004)  # its own clock
    service.publish("A", 2, now + 0.2)
    wait_until(lambda: len(service.groups.groups) == 2, 10, "the first two windows")
    service.publish("A", 3, now + 0.3)
    time.sleep(0.3)
    assert len(service.groups.groups) == 2  # B might still send its frame at 0.2 s
    service.publish("B", 2, now + 0.304)  # B's next frame: the one at 0.2 s was lost
    wait_until(lambda: len(service.groups.groups) == 4, 10, "the windows after the loss")
    assert [cameras for _, cameras in service.groups.groups] == [
        ["A", "B"],
        ["A", "B"],
        ["A"],
        ["A", "B"],
    ]
    stats = service.service.stats()
    assert stats["late"] == 0 and stats["processed"] == 7
