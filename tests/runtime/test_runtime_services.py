"""Camera node, detection sources, matcher-service ordering, two planes, and the CLIs."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from waiting import wait_until

from cblrs.camera import Camera
from cblrs.cli.main import main
from cblrs.datasets import load_scene
from cblrs.detections import CameraMessage, Detections
from cblrs.edge import make_message
from cblrs.errors import CblrsError, DatasetError
from cblrs.matching import make_matcher
from cblrs.pipeline import scene_planes
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.reference import render_reference
from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
from cblrs.runtime.camera.sources import (
    ColourBlobDetector,
    Detector,
    SourceFrame,
    YoloDetector,
    aicity_source,
    detections_from_ultralytics,
    image_folder_source,
    mot_source,
    scene_source,
    video_source,
)
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.matcher_state import ServiceClock
from cblrs.runtime.matcher.retrack import RetrackPolicy
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_schema import LATE, PENDING, PROCESSED
from cblrs.runtime.matcher.tracker_process import TrackerProcessError
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.protocol import Will
from cblrs.runtime.transport.topics import detections_topic, matcher_status_topic, status_topic
from cblrs.runtime.wire import decode_message, decode_status, encode_message, encode_status

PLANE = 1


@pytest.fixture(scope="module")
def small_world():
    """A 320x240 camera looking at a 40 m x 40 m plane, and its reference image."""
    camera = Camera.from_pose("cam1", (0, -10, 8), 90, 35, 450, (320, 240))
    plane = PlaneSpec(PLANE, (-20, -5), 40, 40)
    return camera, render_reference(camera, plane)


# -- detection sources ----------------------------------------------------------------


def test_mot_source_fills_frames_without_detections(tmp_path):
    path = tmp_path / "det.txt"
    path.write_text(
        "# frame,id,x,y,w,h,conf\n5,1,10,20,30,40,0.5\n5,2,0,0,1,1,-1\n"
        "15,1,11,21,30,40,0.9\n20,1,12,21,30,40,0.9\n"
    )
    frames = list(mot_source(path, fps=10))
    assert [frame.frame for frame in frames] == [5, 10, 15, 20]
    assert [frame.timestamp for frame in frames] == [0.5, 1.0, 1.5, 2.0]
    assert [len(frame.detections) for frame in frames] == [2, 0, 1, 1]
    np.testing.assert_array_equal(frames[0].detections.xyxy[0], [10, 20, 40, 60])
    np.testing.assert_array_equal(frames[0].detections.confidence, [0.5, 1.0])
    np.testing.assert_array_equal(frames[0].detections.object_id, [1, 2])


@pytest.mark.parametrize(
    ("text", "step", "expected"),
    [
        ("", None, []),
        ("3,1,0,0,1,1\n", None, [3]),
        ("1,1,0,0,1,1\n4,1,0,0,1,1\n", 1, [1, 2, 3, 4]),
        ("0,1,0,0,1,1\n10,1,0,0,1,1\n4,1,0,0,1,1\n", None, [0, 2, 4, 6, 8, 10]),
    ],
)
def test_mot_source_frame_steps(tmp_path, text, step, expected):
    path = tmp_path / "det.txt"
    path.write_text(text)
    assert [frame.frame for frame in mot_source(path, fps=1, frame_step=step)] == expected


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1,2,3\n", "data line 1 has 3 fields; a MOT"),
        ("1,2,3,4,5,x\n", "data line 1 is not numeric"),
        ("1,2,3,4,5,nan\n", "contains NaN or infinite values"),
    ],
)
def test_mot_source_errors(tmp_path, text, message):
    path = tmp_path / "det.txt"
    path.write_text(text)
    with pytest.raises(DatasetError, match=message):
        list(mot_source(path, fps=10))


def test_missing_detections_file(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        list(mot_source(tmp_path / "none.txt", fps=10))


def test_aicity_source_keeps_one_camera(tmp_path):
    path = tmp_path / "aicity.txt"
    path.write_text("1 7 0 10 20 30 40 1.0 2.0\n2 8 0 0 0 5 5 0 0\n1 7 1 12 20 30 40 1.1 2.0\n")
    frames = list(aicity_source(path, fps=30, camera_number=1))
    assert [frame.frame for frame in frames] == [0, 1]
    np.testing.assert_array_equal(frames[1].detections.xyxy, [[12, 20, 42, 60]])
    with pytest.raises(DatasetError, match=r"no rows of camera 3; it has \[1, 2\]"):
        list(aicity_source(path, fps=30, camera_number=3))


def _draw_frames(folder, count: int) -> list[list[tuple[int, int, int, int]]]:
    """PNG frames with red rectangles; returns the expected boxes (x0, y0, x1, y1) per frame."""
    folder.mkdir(parents=True, exist_ok=True)
    expected = []
    for index in range(count):
        image = np.full((240, 320, 3), 40, np.uint8)
        boxes = [(60 + 10 * index, 100, 80 + 10 * index, 160), (200, 120 - index, 230, 200)]
        if index == count - 1:
            boxes = []  # a frame where nothing is seen
        for x0, y0, x1, y1 in boxes:
            image[y0:y1, x0:x1] = (0, 0, 255)  # BGR red
        cv2.imwrite(str(folder / f"{index:04d}.png"), image)
        expected.append(boxes)
    return expected


def test_image_folder_with_blob_detector(tmp_path):
    expected = _draw_frames(tmp_path / "frames", 4)
    detector = ColourBlobDetector((255, 0, 0), tolerance=10, min_area=10)
    assert isinstance(detector, Detector)
    frames = list(image_folder_source(tmp_path / "frames", detector, fps=5))
    assert [frame.timestamp for frame in frames] == [0.0, 0.2, 0.4, 0.6]
    for frame, boxes in zip(frames, expected, strict=True):
        np.testing.assert_array_equal(frame.detections.xyxy, np.array(boxes, float).reshape(-1, 4))


def test_video_source_with_blob_detector(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (320, 240))
    for index in range(5):
        image = np.zeros((240, 320, 3), np.uint8)
        image[100:140, 50 + 10 * index:70 + 10 * index] = (0, 0, 255)
        writer.write(image)
    writer.release()
    detector = ColourBlobDetector((255, 0, 0), tolerance=60, min_area=50)
    frames = list(video_source(path, detector))
    assert [frame.frame for frame in frames] == [0, 1, 2, 3, 4]
    assert [frame.timestamp for frame in frames] == pytest.approx([0, 0.1, 0.2, 0.3, 0.4])
    centres = [frame.detections.xyxy[:, [0, 2]].mean() for frame in frames]
    assert [len(frame.detections) for frame in frames] == [1] * 5
    assert np.diff(centres) == pytest.approx([10] * 4, abs=2)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda p: list(image_folder_source(p / "none", ColourBlobDetector((1, 2, 3)), 5)),
         "does not exist"),
        (lambda p: list(image_folder_source(p, ColourBlobDetector((1, 2, 3)), 5)),
         "holds no images"),
        (lambda p: list(video_source(p / "none.avi", ColourBlobDetector((1, 2, 3)))),
         "video file .* does not exist"),
        (lambda p: ColourBlobDetector((300, 0, 0)), "three values 0..255"),
        (lambda p: YoloDetector(p / "yolo.pt"), "nothing is downloaded at run time"),
    ],
)
def test_source_and_detector_errors(tmp_path, call, message):
    with pytest.raises(CblrsError, match=message):
        call(tmp_path)


class _FakeTensor:
    """What ultralytics gives: a tensor with ``.cpu().numpy()``."""

    def __init__(self, values):
        self._values = np.asarray(values)

    def cpu(self):
        return self

    def numpy(self):
        return self._values


def test_ultralytics_results_map_to_detections():
    result = SimpleNamespace(
        names={0: "person", 2: "car", 15: "cat", 7: "truck"},
        boxes=SimpleNamespace(
            xyxy=_FakeTensor([[1, 2, 3, 4], [5, 6, 7, 8], [0, 0, 1, 1], [9, 9, 19, 19]]),
            conf=_FakeTensor([0.9, 0.8, 0.7, 0.6]),
            cls=_FakeTensor([0.0, 2.0, 15.0, 7.0]),
        ),
    )
    detections = detections_from_ultralytics(result)
    np.testing.assert_array_equal(detections.xyxy, [[1, 2, 3, 4], [5, 6, 7, 8], [9, 9, 19, 19]])
    np.testing.assert_array_equal(detections.confidence, [0.9, 0.8, 0.6])
    np.testing.assert_array_equal(detections.class_id, [0, 1, 5])  # person, car, truck
    empty = SimpleNamespace(names={0: "person"}, boxes=SimpleNamespace(
        xyxy=_FakeTensor(np.zeros((0, 4))), conf=_FakeTensor([]), cls=_FakeTensor([])))
    assert len(detections_from_ultralytics(empty)) == 0
    assert len(detections_from_ultralytics(SimpleNamespace(names={}, boxes=None))) == 0


def test_scene_source_is_one_camera_of_a_dataset(wildtrack_root):
    scene = load_scene(wildtrack_root).select_frames(0, 20)
    frames = list(scene_source(scene, "CVLab3"))
    assert [frame.frame for frame in frames] == scene.frames.tolist()
    assert frames[2].detections is scene.detections[2][2]
    with pytest.raises(DatasetError, match="no camera 'CVLab9'"):
        list(scene_source(scene, "CVLab9"))


# -- camera node -------------------------------------------------------------------------


def _collector(broker: InProcessBroker):
    received: list[tuple[str, bytes, bool]] = []
    subscriber = InProcessTransport(broker, "collector")
    subscriber.subscribe(
        "cblrs/#", lambda d: (received.append((d.topic, d.payload, d.retain)), d.ack())
    )
    subscriber.connect()
    return received


def _frames(count: int, detections: Detections | None = None) -> list[SourceFrame]:
    if detections is None:
        detections = Detections(np.array([[150.0, 100, 170, 200]]))
    return [SourceFrame(10 + index, 1.0 + 0.5 * index, detections) for index in range(count)]


@pytest.mark.parametrize("realtime", [False, True], ids=["fast", "paced"])
def test_a_camera_stopped_before_its_source_ended_does_not_end_its_stream(small_world,
                                                                        realtime):
    """A signal stops the node mid-replay (fast, or in a paced wait for the next frame's
    time): everything sent is acknowledged, yet the stream goes on after a restart, so its
    "offline" carries no timestamp (a matcher run --until-cameras-offline must keep waiting;
    cblrs up's restart once ended early so)."""
    _, reference = small_world
    broker = InProcessBroker()
    received = _collector(broker)
    transport = InProcessTransport(broker, "cam1", persistent=False,
                                   will=Will(*camera_last_will(PLANE, "cam1")))
    node = CameraNode(transport, PLANE, "cam1", reference, confirm_timeout_s=0,
                      epoch=time.time() - 1.5 if realtime else 1000.0, realtime=realtime)

    def frames():
        for index, frame in enumerate(_frames(10)):  # frames 0.5 s apart from 1.0 s
            if index == 3:
                if realtime:  # the next frame is due in about 1 s: stop in that wait
                    threading.Timer(0.3, node.stop).start()
                else:
                    node.stop()
            yield frame

    report = node.run(frames())
    transport.close()
    wait_until(lambda: any(topic == status_topic(PLANE, "cam1") and
                           decode_status(payload).state == "offline"
                           for topic, payload, _ in received), 5, "the offline status")
    assert report.messages == 3 and report.acknowledged == 3
    statuses = [decode_status(payload) for topic, payload, _ in received
                if topic == status_topic(PLANE, "cam1")]
    assert statuses[-1].state == "offline" and statuses[-1].timestamp is None


def test_camera_node_publishes_status_and_messages(small_world):
    _, reference = small_world
    broker = InProcessBroker()
    received = _collector(broker)
    will = Will(*camera_last_will(PLANE, "cam1"))
    transport = InProcessTransport(broker, "cam1", persistent=False, will=will)
    node = CameraNode(transport, PLANE, "cam1", reference, epoch=1000.0, first_sequence=7)
    report = node.run(_frames(3))
    transport.close()
    wait_until(lambda: len(received) >= 5, 5, "all messages")
    time.sleep(0.1)
    topics = [topic for topic, _, _ in received]
    assert topics[0] == status_topic(PLANE, "cam1")
    assert topics[1:4] == [detections_topic(PLANE, "cam1")] * 3
    assert decode_status(received[0][1]).state == "online"
    # One final, timestamped "offline": closing does not publish the untimestamped will
    # again (it would hide the end of the stream from a restarted matcher).
    assert len(received) == 5 and topics[4] == status_topic(PLANE, "cam1")
    final = decode_status(received[4][1])
    assert final.state == "offline" and final.timestamp is not None
    messages = [decode_message(payload, now=1002.0) for _, payload, _ in received[1:4]]
    assert [message.sequence for message in messages] == [7, 8, 9]
    assert [message.timestamp for message in messages] == [1001.0, 1001.5, 1002.0]
    expected = make_message("cam1", 7, 1001.0, 10, _frames(1)[0].detections, reference)
    np.testing.assert_array_equal(messages[0].colour, expected.colour)
    assert messages[0].colour[0, 2] == PLANE  # the box's foot sees the plane
    assert (report.messages, report.detections, report.located) == (3, 3, 3)
    assert (report.first_sequence, report.next_sequence, report.flushed) == (7, 10, True)


@pytest.mark.parametrize(
    ("realtime", "speed", "epoch", "timestamps", "expected"),
    [
        (True, 2.0, 500.0, [1.0, 2.0], [500.5, 501.0]),  # --speed 2 halves recorded times
        (False, 1.0, None, [1.0, 2.0, 4.0], [997.0, 998.0, 1000.0]),  # the replay ends "now"
        (False, 1.0, 500.0, [1.0, 2.0], [501.0, 502.0]),
        (True, 1.0, None, [1.0, 1.001], [1000.0, 1000.001]),  # the first frame is "now"
        (False, 1.0, None, [None, None], [1000.0, 1000.0]),  # live frames: stamped on capture
        (False, 1.0, None, [], []),
    ],
)
def test_capture_time_mapping(small_world, realtime, speed, epoch, timestamps, expected):
    _, reference = small_world
    broker = InProcessBroker()
    received = _collector(broker)
    transport = InProcessTransport(broker, "cam1", persistent=False)
    node = CameraNode(
        transport, PLANE, "cam1", reference, realtime=realtime, epoch=epoch,
        speed=speed, clock=lambda: 1000.0,
    )
    frames = [SourceFrame(index, ts, Detections.empty()) for index, ts in enumerate(timestamps)]
    node.run(frames)
    wait_until(lambda: len(received) >= len(timestamps) + 2, 5, "all messages")
    times = [
        decode_message(payload, now=1000.0).timestamp
        for topic, payload, _ in received if topic.endswith("/detections")
    ]
    assert times == pytest.approx(expected, abs=1e-9)


def test_camera_node_stop_ends_cleanly(small_world):
    _, reference = small_world
    broker = InProcessBroker()
    received = _collector(broker)
    transport = InProcessTransport(broker, "cam1", persistent=False)
    node = CameraNode(transport, PLANE, "cam1", reference, epoch=1000.0)

    def frames():
        for index, frame in enumerate(_frames(100)):
            if index == 5:
                node.stop()
            yield frame

    report = node.run(frames())
    wait_until(lambda: len(received) >= 7, 5, "the final status")
    assert report.messages == 5
    assert decode_status(received[-1][1]).state == "offline"


def test_camera_queues_while_the_broker_is_away(small_world, start_mosquitto):
    _, reference = small_world
    broker = start_mosquitto()
    got: list[int] = []
    subscriber = MqttTransport("queue-subscriber", broker.settings(), persistent=True)

    def on_message(delivery) -> None:
        got.append(decode_message(delivery.payload, now=time.time()).sequence)
        delivery.ack()

    subscriber.subscribe(detections_topic(PLANE, "cam1"), on_message)
    subscriber.connect()
    broker.stop()  # the persistent session of the subscriber is saved with the broker's state
    camera = MqttTransport("queue-camera", broker.settings(), persistent=False)
    camera.connect(wait=False)
    node = CameraNode(camera, PLANE, "cam1", reference, epoch=time.time(), flush_timeout_s=20)
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault("report", node.run(
        _frames(20), connect=False)))
    thread.start()
    wait_until(lambda: camera.pending() >= 20, 10, "publishes queued while the broker is away")
    broker.start()
    thread.join(30)
    camera.close()
    wait_until(lambda: len(got) == 20, 20, "every queued message")
    subscriber.close()
    assert result["report"].flushed
    assert sorted(got) == list(range(20))


# -- matcher service: ordering window, late messages, restarts -----------------------------


class _Groups:
    """Observer recording each released group as (timestamp, camera ids)."""

    def __init__(self):
        self.groups: list[tuple[float, list[str]]] = []

    def on_group(self, timestamp, messages, tracks, wall_time):
        self.groups.append((timestamp, [message.camera_id for message in messages]))


def _planes():
    return PlaneSet([PlaneSpec(PLANE, (0.0, 0.0), 20.0, 20.0)])


def _message(camera: str, sequence: int, timestamp: float) -> bytes:
    message = CameraMessage(
        camera, sequence, timestamp, sequence, np.array([[0.0, 0, 10, 10]]), np.array([0.9]),
        np.array([0]), np.array([[1000 + 100 * sequence, 2000, PLANE]]),
    )
    return encode_message(message, PLANE)


@pytest.fixture
def ordering(tmp_path):
    """Factory for an in-process service with cameras A and B plus a publisher."""
    broker = InProcessBroker()
    started = []

    def start(window_s: float, database: str = "matcher.db", **options):
        groups = _Groups()
        store = RuntimeStore(tmp_path / database)
        service = MatcherService(
            InProcessTransport(broker, "matcher"), store,
            make_matcher("fusion", _planes(), ["A", "B"]), PLANE, ["A", "B"],
            window_s=window_s, observer=groups, **options,
        )
        service.start()
        started.append((service, store))
        return service, store, groups

    publisher = InProcessTransport(broker, "publisher", persistent=False)
    publisher.connect()

    def publish(camera: str, sequence: int, timestamp: float) -> None:
        publisher.publish(detections_topic(PLANE, camera), _message(camera, sequence, timestamp))

    def status(camera: str, state: str, timestamp: float | None, retain: bool = False) -> None:
        payload = encode_status(camera, state, timestamp=timestamp)
        publisher.publish(status_topic(PLANE, camera), payload, retain=retain)

    yield SimpleNamespace(start=start, publish=publish, status=status, broker=broker)
    for service, store in started:
        try:
            service.close()
        finally:
            store.close()


def test_group_waits_for_every_camera(ordering):
    _, store, groups = ordering.start(window_s=60)
    now = time.time()
    ordering.publish("A", 0, now)
    ordering.publish("A", 1, now + 1)
    wait_until(lambda: store.counters().get("accepted") == 2, 5, "two messages")
    assert groups.groups == []
    ordering.publish("B", 0, now)
    wait_until(lambda: len(groups.groups) == 1, 5, "the first group")
    ordering.publish("B", 1, now + 1)
    wait_until(lambda: len(groups.groups) == 2, 5, "the second group")
    assert groups.groups == [(now, ["A", "B"]), (now + 1, ["A", "B"])]


def test_silent_camera_is_given_up_after_the_window_and_then_late(ordering):
    """B's message comes after its time was released: counted late, then re-tracked (one
    re-tracking from the empty tracker's snapshot) and processed."""
    service, store, groups = ordering.start(window_s=0.2)
    now = time.time()
    ordering.publish("A", 0, now)
    ordering.publish("A", 1, now + 1)
    wait_until(lambda: len(groups.groups) == 2, 5, "both groups after the window")
    assert groups.groups == [(now, ["A"]), (now + 1, ["A"])]
    ordering.publish("B", 0, now)  # too late: its timestamp was released
    wait_until(lambda: store.counters().get("late") == 1, 5, "a late message")
    wait_until(service.drained, 10, "the late message to be re-tracked")
    assert [stored.status for stored in store.messages() if stored.message.camera_id == "B"] == [
        PROCESSED
    ]
    stats = service.stats()
    assert (stats["late"], stats["late_tracked"], stats["retracks"]) == (1, 1, 1), stats
    assert stats["processed"] == 3 and stats["late_untracked"] == 0
    assert groups.groups == [(now, ["A"]), (now + 1, ["A"])], "corrections are no new groups"


def test_a_late_message_older_than_every_snapshot_stays_untracked(ordering):
    """Only the newest snapshot is kept (after A's third message): B's message from before
    it cannot be re-tracked; it stays late and is counted ``late_untracked``."""
    service, store, groups = ordering.start(
        window_s=0.2, retrack=RetrackPolicy(snapshot_interval_s=0.5, max_snapshots=1,
                                            delay_s=0.1))
    now = time.time()
    for sequence in range(3):
        ordering.publish("A", sequence, now + sequence)
    wait_until(lambda: len(groups.groups) == 3, 5, "A's groups after the window")
    ordering.publish("B", 0, now)
    wait_until(lambda: store.counters().get("late_untracked") == 1 and service.drained(), 10,
               "the late message to be looked at")
    assert [stored.status for stored in store.messages() if stored.message.camera_id == "B"] == [
        LATE
    ]
    stats = service.stats()
    assert (stats["late"], stats["late_tracked"], stats["retracks"]) == (1, 0, 0), stats
    assert stats["processed"] == 3


def test_a_restarted_matcher_tracks_the_late_messages_it_holds(ordering):
    """Stopped before its re-tracking delay was over, the matcher leaves B's message late;
    restarted on the same database, it re-tracks it."""
    service, store, groups = ordering.start(window_s=0.2, retrack=RetrackPolicy(delay_s=600))
    now = time.time()
    ordering.publish("A", 0, now)
    ordering.publish("A", 1, now + 1)
    wait_until(lambda: len(groups.groups) == 2, 5, "A's groups after the window")
    ordering.publish("B", 0, now)
    wait_until(lambda: store.counters().get("late") == 1, 5, "a late message")
    service.stop()
    service.transport.close(unclean=True)
    assert store.status_counts() == {PROCESSED: 2, LATE: 1}
    again, store_again, _ = ordering.start(window_s=0.2, database="matcher.db",
                                           retrack=RetrackPolicy(delay_s=0.1))
    wait_until(lambda: store_again.counters().get("late_tracked") == 1 and again.drained(), 10,
               "the late message to be re-tracked after the restart")
    assert store_again.status_counts() == {PROCESSED: 3}


def test_clean_offline_camera_is_not_waited_for(ordering):
    _, _, groups = ordering.start(window_s=60)
    now = time.time()
    ordering.status("B", "offline", now)
    ordering.publish("A", 0, now)
    wait_until(lambda: len(groups.groups) == 1, 5, "the group")
    assert groups.groups == [(now, ["A"])]


@pytest.mark.parametrize(
    ("state", "timestamp_offset", "retain"),
    [
        ("offline", None, False),  # a last will: the connection dropped, the stream goes on
        ("offline", -3600.0, True),  # a retained "offline" from an earlier run
    ],
)
def test_wills_and_stale_offline_do_not_end_a_stream(ordering, state, timestamp_offset, retain):
    now = time.time()
    timestamp = None if timestamp_offset is None else now + timestamp_offset
    ordering.status("B", state, timestamp, retain=retain)
    _, store, groups = ordering.start(window_s=60)
    ordering.publish("A", 0, now)
    wait_until(lambda: store.counters().get("accepted") == 1, 5, "A's message")
    time.sleep(0.2)
    assert groups.groups == []
    ordering.publish("B", 0, now)
    wait_until(lambda: len(groups.groups) == 1, 5, "the group")
    assert groups.groups == [(now, ["A", "B"])]


def test_restart_resumes_pending_messages_and_state(ordering, tmp_path):
    service, store, groups = ordering.start(window_s=60)
    now = time.time()
    for sequence in range(2):
        ordering.publish("A", sequence, now + sequence)
        ordering.publish("B", sequence, now + sequence)
    ordering.publish("A", 2, now + 2)
    wait_until(lambda: len(groups.groups) == 2 and store.counters()["accepted"] == 5, 5, "two")
    service.stop()  # no flush: A's third message stays pending in the store
    service.transport.close(unclean=True)
    again, store_again, groups_again = ordering.start(window_s=60, database="matcher.db")
    assert again.buffered() == 1
    ordering.publish("B", 2, now + 2)
    ordering.publish("A", 1, now + 1)  # a redelivery of something already processed
    wait_until(lambda: len(groups_again.groups) == 1, 5, "the resumed group")
    wait_until(lambda: store_again.counters().get("duplicates") == 1, 5, "the duplicate")
    assert groups_again.groups == [(now + 2, ["A", "B"])]
    counters = store_again.counters()
    assert (counters["processed"], counters["groups"]) == (6, 3)
    assert store_again.status_counts() == {"processed": 6}


# -- matcher service: the tracker process ----------------------------------------------------


class _FailingMatcher:
    """A matcher whose update raises (module level, so it pickles into the tracker process)."""

    def update(self, timestamp, messages):
        raise ValueError("the update exploded")

    def get_state(self):
        return None

    def set_state(self, state):
        pass


@pytest.fixture
def tracker_service(tmp_path):
    """Factory for an in-process service with cameras A and B; stops leftovers at the end."""
    broker = InProcessBroker()
    started = []

    def start(matcher=None):
        store = RuntimeStore(tmp_path / "matcher.db")
        groups = _Groups()
        service = MatcherService(
            InProcessTransport(broker, "matcher"), store,
            matcher or make_matcher("fusion", _planes(), ["A", "B"]), PLANE, ["A", "B"],
            window_s=60, observer=groups,
        )
        service.start()
        started.append((service, store))
        return service, store, groups

    publisher = InProcessTransport(broker, "publisher", persistent=False)
    publisher.connect()

    def publish(sequence: int, timestamp: float, cameras=("A", "B")) -> None:
        for camera in cameras:
            publisher.publish(
                detections_topic(PLANE, camera), _message(camera, sequence, timestamp)
            )

    yield SimpleNamespace(start=start, publish=publish)
    for service, store in started:
        try:
            service.close()
        except RuntimeError:  # a test's failed service: already checked there
            pass
        finally:
            store.close()


def test_tracker_process_failure_stops_the_service_and_is_raised(tracker_service):
    service, store, groups = tracker_service.start(_FailingMatcher())
    tracker_service.publish(0, time.time())
    wait_until(service.failed, 30, "the service to notice the failed update")
    with pytest.raises(RuntimeError) as caught:
        service.close()
    cause = caught.value.__cause__
    assert isinstance(cause, TrackerProcessError)
    assert "ValueError: the update exploded" in str(cause)
    assert groups.groups == []
    assert store.status_counts() == {PENDING: 2}, "nothing may be committed for the group"
    assert not service._tracker.process.is_alive()


def test_killed_tracker_process_fails_the_service_and_a_restart_resumes(tracker_service):
    service, _, groups = tracker_service.start()
    now = time.time()
    tracker_service.publish(0, now)
    wait_until(lambda: len(groups.groups) == 1, 30, "the first group")
    os.kill(service._tracker.process.pid, signal.SIGKILL)
    wait_until(service.failed, 30, "the service to notice the dead tracker process")
    tracker_service.publish(1, now + 1)  # queued for the service's session meanwhile
    with pytest.raises(RuntimeError) as caught:
        service.stop()
    assert "exited (code -9)" in str(caught.value.__cause__)
    service.transport.close(unclean=True)
    again, store_again, groups_again = tracker_service.start()
    wait_until(lambda: len(groups_again.groups) == 1, 30, "the group after the restart")
    again.close(flush=True)
    assert groups_again.groups == [(now + 1, ["A", "B"])]
    counters = store_again.counters()
    assert (counters["processed"], counters["groups"], counters.get("duplicates", 0)) == (4, 2, 0)
    assert store_again.status_counts() == {PROCESSED: 4}


def test_clean_stop_ends_the_tracker_process_after_committing(tracker_service):
    service, store, groups = tracker_service.start()
    tracker_service.publish(0, time.time(), cameras=("A",))  # waits for B: flushed at stop
    wait_until(lambda: store.counters().get("accepted") == 1, 30, "the message")
    service.close(flush=True)
    assert service._tracker.process.exitcode == 0
    assert len(groups.groups) == 1
    assert store.status_counts() == {PROCESSED: 1}
    assert store.counters()["groups"] == 1


def test_service_clock_stands_still_while_disconnected():
    state = {"now": 100.0, "connected": True}
    clock = ServiceClock(lambda: state["connected"], lambda: state["now"])
    assert clock() == 100.0
    state["connected"] = False
    assert clock() == 100.0
    state["now"] = 160.0
    assert clock() == 100.0
    state["connected"] = True
    assert clock() == 100.0
    state["now"] = 161.0
    assert clock() == 101.0


# -- two planes, two matchers on one broker ------------------------------------------------


def test_two_planes_two_matchers_one_broker(wildtrack_root, mosquitto, tmp_path):
    scene = load_scene(wildtrack_root).select_frames(0, 45)
    names = scene.camera_names
    split = {1: names[:4], 2: names[4:]}
    ground = scene_planes(scene)[0]
    planes = {plane_id: PlaneSet([replace(ground, plane_id=plane_id)]) for plane_id in split}
    services = {}
    for plane_id, cameras in split.items():
        store = RuntimeStore(tmp_path / f"plane{plane_id}.db")
        service = MatcherService(
            MqttTransport(f"two-planes-matcher-{plane_id}", mosquitto.settings()), store,
            make_matcher("fusion", planes[plane_id], cameras), plane_id, cameras, window_s=5,
        )
        service.start()
        services[plane_id] = (service, store)
    epoch = float(int(time.time()) - 600)
    for plane_id, cameras in split.items():
        for name in cameras:
            index = names.index(name)
            reference = render_reference(scene.cameras[index], planes[plane_id])
            transport = MqttTransport(
                f"two-planes-{name}", mosquitto.settings(), persistent=False,
                will=Will(*camera_last_will(plane_id, name)),
            )
            CameraNode(transport, plane_id, name, reference, epoch=epoch).run(
                scene_source(scene, index)
            )
            transport.close()
    for plane_id, (service, store) in services.items():
        wait_until(lambda s=service: s.cameras_done() and s.drained(), 30, f"plane {plane_id}")
        service.close(flush=True)
        stored_cameras = {item.message.camera_id for item in store.messages()}
        assert stored_cameras == set(split[plane_id])
        counters = store.counters()
        assert counters["processed"] == len(scene.frames) * len(split[plane_id])
        assert counters.get("late", 0) == 0 and counters.get("rejected.unknown_camera", 0) == 0
        assert len(store.tracks()) > 0
        store.close()


# -- command line ------------------------------------------------------------------------


def test_camera_command_replays_a_mot_file(small_world, mosquitto, tmp_path, capsys):
    _, reference = small_world
    reference_path = reference.save(tmp_path / "cam1.png")
    detections = tmp_path / "cam1.txt"
    detections.write_text("1,1,150,100,20,100,0.9\n2,1,152,100,20,100,0.9\n4,1,156,100,20,100,0.9\n")
    code = main([
        "camera", "--camera", "cam1", "--reference", str(reference_path),
        "--detections", str(detections), "--fps", "10", "--epoch", str(time.time()),
        "--broker", f"127.0.0.1:{mosquitto.port}", "--json", "--spool",
        str(tmp_path / "spool.db"), "--confirm-timeout", "0",
    ])
    report = json.loads(capsys.readouterr().out)
    assert code == 0  # --confirm-timeout 0: the broker's acknowledgement is enough
    assert (report["frames"], report["messages"], report["detections"]) == (4, 4, 3)
    assert report["located"] == 3 and report["flushed"]
    # No matcher confirmed them: they stay in the spool until one does.
    assert report["unconfirmed"] == 4 and not report["confirmed_all"]


def test_a_replay_that_starts_late_says_when_its_first_frame_goes_out(small_world, mosquitto,
                                                                        tmp_path):
    # Issue 21: data whose times start at 100 s, replayed with the README's recipe
    # (--realtime --epoch now+5), sent nothing for 105 s without a word. Now the camera says
    # when its first frame is due, and how to start at once; that --epoch starts at once.
    _, reference = small_world
    reference_path = reference.save(tmp_path / "cam1.png")
    detections = tmp_path / "cam1.txt"
    detections.write_text("".join(f"{frame},1,150,100,20,100,0.9\n" for frame in (1000, 1001)))

    def camera(epoch: float, spool: str) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-m", "cblrs.cli.main", "camera", "--camera", "cam1", "--reference",
             str(reference_path), "--detections", str(detections), "--fps", "10",
             "--realtime", "--epoch", f"{epoch:.0f}", "--broker", f"127.0.0.1:{mosquitto.port}",
             "--spool", str(tmp_path / spool), "--confirm-timeout", "0", "--json"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    late = camera(time.time() + 5, "late.db")
    said: list[str] = []
    reader = threading.Thread(target=lambda: said.extend(late.stderr), daemon=True)
    reader.start()
    try:
        wait_until(lambda: any("first frame" in line for line in said), 60,
                   "the camera to say when its first frame is due")
        line = next(line for line in said if "first frame" in line)
        assert "WARNING" in line, line
        assert re.search(r"camera cam1: the first frame \(recorded at 100 s\) is due at "
                         r"\d\d:\d\d:\d\d UTC \(--epoch \+ its time\), in (\d+) s; nothing is "
                         r"sent before; the recording starts at 100 s, so to start it at once "
                         r"give every camera --epoch \$\(\( \$\(date \+%s\) \+ 5 - 100 \)\)$",
                         line.strip()), line
        # 105 s less however long the camera took to start on a busy machine.
        waiting = int(re.search(r"in (\d+) s;", line)[1])
        assert 10 < waiting <= 105, line
        assert late.poll() is None  # still waiting, as it said
    finally:
        late.terminate()
        late.wait(30)
        reader.join(10)

    # The suggested epoch: the replay starts within seconds.
    started = time.monotonic()
    prompt = camera(time.time() + 5 - 100, "prompt.db")
    out, err = prompt.communicate(timeout=60)
    assert prompt.returncode == 0, err
    assert json.loads(out)["messages"] == 2
    assert time.monotonic() - started < 30
    # At most a note that the first frame is due in a few seconds (none when the camera took
    # that long to start): no warning, no advice.
    said = [line for line in err.splitlines() if "first frame" in line]
    assert len(said) <= 1 and all(" INFO " in line and "to start it at once" not in line
                                  for line in said), said


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["camera", "--camera", "cam1", "--reference", "REF"], "give exactly one source"),
        (["camera", "--camera", "cam1", "--reference", "REF", "--detections", "x.txt"],
         "--detections needs --fps"),
        (["camera", "--camera", "cam/1", "--reference", "REF", "--detections", "x"],
         "not usable in MQTT topics"),
        (["camera", "--camera", "cam1", "--reference", "REF", "--images", "IMG", "--detector",
          "yolo"], "needs --weights"),
        (["matcher", "--db", "x.db"], "give --db FILE and --references DIR"),
        (["matcher", "--stats", "missing.db"], "does not exist"),
        (["matcher", "--db", "x.db", "--references", "REFS", "--option", "oops"],
         "must be KEY=VALUE"),
        (["matcher", "--db", "x.db", "--references", "REFS", "--plane", "3"],
         r"--plane 3 is not in the references \(planes \[1\]\)"),
        # issue 10, item 9: every bad value is one sentence, before anything starts
        (["matcher", "--db", "x.db", "--references", "REFS", "--window", "-1"],
         r"--window must be a finite number of at least 0, got -1\.0\."),
        (["matcher", "--db", "x.db", "--references", "REFS", "--window", "nan"],
         r"--window must be a finite number of at least 0, got nan\."),
        (["matcher", "--db", "x.db", "--references", "REFS", "--max-future", "nan"],
         r"--max-future must be a finite number of at least 0"),
        (["matcher", "--db", "x.db", "--references", "REFS", "--max-age", "0"],
         r"--max-age must be a finite number greater than 0"),
        (["matcher", "--db", "x.db", "--references", "REFS", "--idle-exit", "-1"],
         r"--idle-exit must be a finite number greater than 0"),
        (["matcher", "--db", "x.db", "--references", "REFS", "--broker", ":99999"],
         r"--broker ':99999' names no host"),
        (["matcher", "--db", "x.db", "--references", "REFS", "--broker", "localhost:99999"],
         r"--broker 'localhost:99999': the port must be a number from 1 to 65535\."),
        (["matcher", "--db", "x.db", "--references", "REFS", "--broker", "localhost:x"],
         r"the port must be a number from 1 to 65535"),
        (["matcher", "--db", "x.db", "--references", "REFS", "--retain-hours", "-2"],
         r"--retain-hours must be a finite number of at least 0"),
        (["matcher", "--db", "missing/x.db", "--references", "REFS"],
         r"the folder .*missing of the database x\.db does not exist; create it first"),
        (["matcher", "--db", "EMPTY", "--references", "REFS"],
         r"EMPTY is an empty file, not a cblrs matcher database"),
        (["matcher", "--stats", "REF"], r"ref\.png is not a SQLite database"),
        (["matcher", "--stats", "DAMAGED"], r"is damaged: SQLite says|not a usable SQLite"),
        (["camera", "--camera", "CVLab1\n", "--reference", "REF", "--detections", "x"],
         r"camera id 'CVLab1\\n' is not usable in MQTT topics"),
        (["camera", "--camera", "cam1", "--reference", "REF", "--detections", "x",
          "--speed", "nan"], r"--speed must be a finite number greater than 0"),
        (["camera", "--camera", "cam1", "--reference", "REF", "--detections", "x",
          "--spool-max-mb", "0"], r"--spool-max-mb must be a finite number greater than 0"),
        (["camera", "--camera", "cam1", "--reference", "REF", "--detections", "x",
          "--broker", "h:0"], r"the port must be a number from 1 to 65535"),
    ],
)
def test_command_line_mistakes(small_world, tmp_path, capsys, monkeypatch, arguments, message):
    _, reference = small_world
    monkeypatch.chdir(tmp_path)
    reference.save(tmp_path / "ref.png")
    (tmp_path / "REFS").mkdir()
    reference.save(tmp_path / "REFS" / "cam1.png")
    (tmp_path / "IMG").mkdir()
    (tmp_path / "EMPTY").write_bytes(b"")
    damaged = tmp_path / "DAMAGED"
    with RuntimeStore(damaged) as store:
        store.add_counters({"received": 1})
    data = bytearray(damaged.read_bytes())
    data[100:] = b"\xff" * (len(data) - 100)  # the header survives, the rest is noise
    damaged.write_bytes(bytes(data))
    arguments = [str(tmp_path / "ref.png") if item == "REF" else item for item in arguments]
    code = main(arguments)
    error = capsys.readouterr().err
    assert code != 0
    assert re.search(message, error), error
    assert "Traceback" not in error and error.count("error:") == 1, error


def test_matcher_stats_reads_a_database(tmp_path, capsys):
    with RuntimeStore(tmp_path / "m.db") as store:
        store.bind({"plane_id": 1, "camera_ids": ["a"], "matcher": "fusion"})
        store.add_counters({"received": 4, "rejected.too_old": 1, "processed": 3})
    assert main(["matcher", "--stats", str(tmp_path / "m.db"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["counters"] == {"processed": 3, "received": 4, "rejected.too_old": 1}
    assert summary["settings"]["camera_ids"] == ["a"]
    assert main(["matcher", "--stats", str(tmp_path / "m.db")]) == 0
    assert "rejected.too_old" in capsys.readouterr().out


def test_matcher_command_stops_cleanly_on_sigterm(small_world, mosquitto, tmp_path):
    _, reference = small_world
    (tmp_path / "refs").mkdir()
    reference.save(tmp_path / "refs" / "cam1.png")
    online = threading.Event()
    watcher = MqttTransport("sigterm-watcher", mosquitto.settings(), persistent=False)

    def on_status(delivery) -> None:
        if decode_status(delivery.payload).state == "online":
            online.set()
        delivery.ack()

    watcher.subscribe(matcher_status_topic(PLANE, "sigterm-matcher"), on_status)
    watcher.connect()
    process = subprocess.Popen(
        [sys.executable, "-m", "cblrs.cli.main", "matcher", "--references",
         str(tmp_path / "refs"), "--db", str(tmp_path / "m.db"), "--client-id",
         "sigterm-matcher", "--broker", f"127.0.0.1:{mosquitto.port}", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        wait_until(online.is_set, 60, "the matcher to come online")
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
        watcher.close()
    assert process.returncode == 0, err
    summary = json.loads(out)
    assert (summary["plane_id"], summary["cameras"], summary["received"]) == (PLANE, 1, 0)


def test_locate_boxes_and_the_camera_agree_on_every_box(small_world, tmp_path, capsys):
    # Issue 10, item 11: one rule for boxes on both sides.
    _, reference = small_world
    path = reference.save(tmp_path / "cam1.png")
    boxes = np.array([
        [150.0, 100, 170, 200],      # a person in view
        [1e12, 1e12, 1e12 + 5, 1e12 + 5],  # entirely outside the image
        [np.nan, 10, 20, 30],        # not finite
        [50.0, 60, 40, 80],          # inverted
        [150.0, 150, 170, 239.5],    # feet on the bottom border: no location
        [-40.0, 100, -10, 200],      # left of the image
    ])
    lines = "\n".join(" ".join(f"{value!r}" for value in row) for row in boxes.tolist())
    (tmp_path / "boxes.txt").write_text(lines.replace("nan", "nan") + "\n")
    assert main(["locate", str(path), "--boxes", str(tmp_path / "boxes.txt"), "--json"]) == 0
    positions = json.loads(capsys.readouterr().out)["positions"]
    broker = InProcessBroker()
    received = _collector(broker)
    node = CameraNode(InProcessTransport(broker, "cam1", persistent=False), PLANE, "cam1",
                      reference, epoch=1000.0)
    report = node.run([SourceFrame(0, 0.0, Detections(boxes))])
    wait_until(lambda: any(t.endswith("/detections") for t, _, _ in received), 5, "the message")
    (payload,) = [p for t, p, _ in received if t.endswith("/detections")]
    message = decode_message(payload, now=1000.0)
    rejected = [row["rejected"] for row in positions]
    assert rejected == [None, "outside_image", "not_finite", "inverted", None, "outside_image"]
    assert report.boxes_rejected == {"outside_image": 2, "not_finite": 1, "inverted": 1}
    kept = [row for row in positions if row["rejected"] is None]
    assert len(message) == len(kept) == 2
    for row, colour in zip(kept, message.colour, strict=True):
        assert (row["camera_sends"] == "location") == bool(colour[2] != 0)
    assert [row["camera_sends"] for row in kept] == ["location", "no location (cut_by_border)"]
    assert all(row["x"] is None for row in positions if row["rejected"])


def test_a_camera_without_any_matcher_keeps_everything(small_world, caplog):
    # MQTT 5 "no matching subscribers" (0x10; the in-process broker answers it, Mosquitto 2.0
    # answers 0): accepted by the broker, delivered to nobody, so the spool keeps it.
    _, reference = small_world
    broker = InProcessBroker()
    node = CameraNode(InProcessTransport(broker, "cam1", persistent=False), PLANE, "cam1",
                      reference, epoch=1000.0, confirm_timeout_s=0.2)
    with caplog.at_level("WARNING", logger="cblrs.runtime.camera.camera_node"):
        report = node.run(_frames(5))
    assert report.flushed and not report.confirmed_all
    assert (report.unconfirmed, report.extra["unrouted"], report.confirmed) == (5, 5, 0)
    assert "no subscriber for cblrs/1/cam1/detections" in caplog.text
    assert report.extra["final_status"] is False  # not the end of the stream for a matcher


def test_a_cameras_report_shows_what_the_backbone_did_to_its_publishes(small_world):
    # The NATS transport counts publishes held back at the camera's stream limit and silent
    # connections it made again (tests/runtime/test_runtime_nats*.py make both happen on a
    # real server); the camera's report (cblrs camera --json) carries them when not zero.
    _, reference = small_world
    broker = InProcessBroker()
    transport = InProcessTransport(broker, "cam1", persistent=False)
    node = CameraNode(transport, PLANE, "cam1", reference, epoch=1000.0, confirm_timeout_s=0.2)
    report = node.run(_frames(2))
    assert "silent_reconnects" not in report.extra
    assert "subject_full_refusals" not in report.extra
    transport.silent_reconnects, transport.subject_full_refusals = 2, 0
    node = CameraNode(transport, PLANE, "cam1", reference, epoch=1000.0, confirm_timeout_s=0.2)
    report = node.run(_frames(2))
    assert report.extra["silent_reconnects"] == 2
    assert "subject_full_refusals" not in report.extra
