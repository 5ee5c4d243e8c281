"""Reliability of the runtime: nothing lost, nothing counted twice, bad input survived.

* the broker is restarted mid-stream (with persistence): every message arrives, is tracked
  once, and the tracks equal an uninterrupted run;
* the matcher process is killed (SIGKILL) mid-stream and restarted on the same database:
  every (camera, sequence) is processed exactly once and the tracks equal an uninterrupted
  run;
* duplicate deliveries are ignored;
* each kind of bad input is rejected, counted by reason, and the matcher keeps going.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from waiting import store_counter, wait_until, wait_while_progressing

from cblrs.datasets import load_scene
from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.pipeline import render_scene_references, scene_planes, track_scene
from cblrs.reference import ReferenceImage
from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
from cblrs.runtime.camera.sources import scene_source
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.protocol import Will
from cblrs.runtime.transport.topics import detections_topic, matcher_status_topic
from cblrs.runtime.wire import ValidationPolicy, decode_status, encode_message

PLANE = 1
FRAMES = (0, 595)  # 120 annotated frames: long enough to interrupt, short enough to be quick
SPEED = 5.0
"""Replay speed of the paced cameras (the 120 frames take 12 s). Faster replays show the
tracker people moving many times faster than walking, and its work grows with that: the
fusion tracker needs 1.6 CPU-s for these frames at speed 5 (1.8 at 1) but 7.0 at 10 and 21
at 25 (``track_scene`` on the sped-up timestamps, time.process_time), which on a loaded
machine, not the restart or the kill, set how long the tests took."""
STALL_S = 20.0
"""The waits for the matcher fail after this long without progress (messages stored or
tracked, cameras finishing), not after a fixed time: on a loaded machine the tracking is
slower, never stuck. It is below the cameras' 30 s resend timer, so a message that only
arrives through that timer fails the test as a stall."""


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory):
    """A WILDTRACK subset and its reference PNGs (saved, then read back)."""
    scene = load_scene(wildtrack_root).select_frames(*FRAMES)
    folder = tmp_path_factory.mktemp("references")
    references = []
    for camera, reference in zip(scene.cameras, render_scene_references(scene), strict=True):
        path = reference.save(folder / f"{camera.name}.png")
        references.append(ReferenceImage.load(path, expected_size=camera.image_size))
    return {"scene": scene, "references": references, "folder": folder}


def expected_tracks(case, epoch: float, speed: float):
    """The uninterrupted in-process run on the same capture times as the paced replay."""
    scene = case["scene"]
    return track_scene(
        replace(scene, timestamps=epoch + scene.timestamps * (1.0 / speed)),
        matcher=make_matcher("fusion", scene_planes(scene), scene.camera_names),
        references=case["references"],
    ).tracks


def start_cameras(case, settings, speed: float, prefix: str) -> tuple[list, float]:
    """One paced camera node per scene camera, each on its own MQTT connection (threads).

    Returns the threads and the shared epoch (the first frame's capture time).
    """
    scene = case["scene"]
    epoch = time.time() + 0.5
    threads = []
    for index, name in enumerate(scene.camera_names):

        def run(index=index, name=name) -> None:
            transport = MqttTransport(
                f"{prefix}-{name}", settings, persistent=False,
                will=Will(*camera_last_will(PLANE, name)),
            )
            transport.connect()
            node = CameraNode(
                transport, PLANE, name, case["references"][index], realtime=True,
                speed=speed, epoch=epoch, flush_timeout_s=30.0,
            )
            node.run(scene_source(scene, index), connect=False)
            transport.close()

        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        threads.append(thread)
    return threads, epoch


def assert_exactly_once(store: RuntimeStore, case, expected) -> None:
    scene = case["scene"]
    messages = len(scene.frames) * len(scene.cameras)
    stored = store.messages()
    keys = {(item.message.camera_id, item.message.sequence) for item in stored}
    expected_keys = {
        (name, sequence) for name in scene.camera_names for sequence in range(len(scene.frames))
    }
    assert keys == expected_keys, "messages lost"
    assert store.status_counts() == {"processed": messages}
    counters = store.counters()
    assert counters["processed"] == messages, "a message was tracked twice"
    assert counters["groups"] == len(scene.frames)
    assert counters.get("late", 0) == 0
    tracks = store.tracks()
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)


def test_broker_restart_mid_stream_loses_nothing(case, start_mosquitto, tmp_path):
    broker = start_mosquitto()
    scene = case["scene"]
    names = scene.camera_names
    store = RuntimeStore(tmp_path / "matcher.db")
    service = MatcherService(
        MqttTransport("restart-matcher", broker.settings()), store,
        make_matcher("fusion", scene_planes(scene), names), PLANE, names, window_s=5.0,
    )
    service.start()
    caught_up = False
    try:
        threads, epoch = start_cameras(case, broker.settings(), speed=SPEED, prefix="restart")
        total = len(scene.frames) * len(names)

        def progress() -> tuple[int, int, int]:
            counters = store.counters()
            return (counters.get("accepted", 0), counters.get("processed", 0),
                    sum(thread.is_alive() for thread in threads))

        wait_while_progressing(
            lambda: store.counters().get("accepted", 0) >= total // 4, progress, STALL_S,
            "a quarter",
        )
        broker.restart()
        restarted_at = store.counters().get("accepted", 0)
        wait_while_progressing(
            lambda: not any(thread.is_alive() for thread in threads)
            and service.cameras_done() and service.drained(),
            progress, STALL_S, "the cameras to finish and the matcher to catch up",
        )
        caught_up = True
    finally:
        # A failed wait must not leave the tracker process working (the interpreter's exit
        # would wait for it): a stop without flush abandons what it holds.
        service.close(flush=caught_up)
    assert restarted_at < total, "the broker restart was not mid-stream"
    assert_exactly_once(store, case, expected_tracks(case, epoch, SPEED))
    store.close()


def _matcher_command(case, broker, database) -> list[str]:
    return [
        sys.executable, "-m", "cblrs.cli.main", "matcher",
        "--references", str(case["folder"]), "--db", str(database),
        "--broker", f"127.0.0.1:{broker.port}", "--client-id", "killed-matcher",
        "--window", "5", "--until-cameras-offline", "--idle-exit", "30", "--json",
    ]


def _cpu_seconds(process: subprocess.Popen) -> float:
    """User + system CPU seconds of a running child so far (0 where /proc is not there)."""
    try:
        with open(f"/proc/{process.pid}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_matcher_killed_mid_stream_resumes_exactly_once(case, start_mosquitto, tmp_path):
    broker = start_mosquitto()
    database = tmp_path / "matcher.db"
    scene = case["scene"]
    total = len(scene.frames) * len(scene.cameras)
    environment = {**os.environ, "PYTHONUNBUFFERED": "1"}
    matcher_online = threading.Event()
    watcher = MqttTransport("killed-watcher", broker.settings(), persistent=False)

    def on_status(delivery) -> None:
        if decode_status(delivery.payload).state == "online":
            matcher_online.set()
        delivery.ack()

    def counts() -> tuple[int, int]:
        return store_counter(database, "accepted"), store_counter(database, "processed")

    def progress(matcher: subprocess.Popen, threads=()) -> tuple:
        # Starting up (imports) shows only as the child's CPU time; a child that waits on a
        # timer or a lost wake-up uses none.
        return (*counts(), sum(thread.is_alive() for thread in threads),
                round(_cpu_seconds(matcher), 1) if matcher.poll() is None else None)

    watcher.subscribe(matcher_status_topic(PLANE, "killed-matcher"), on_status)
    watcher.connect()
    # Files, not pipes: nobody reads them while the matchers run, and a full pipe blocks.
    first_log = open(tmp_path / "first.log", "w")  # closed below
    first = subprocess.Popen(_matcher_command(case, broker, database), stdout=first_log,
                             stderr=subprocess.STDOUT, env=environment)
    try:
        # Its session exists once it has subscribed, which precedes its "online" status.
        wait_while_progressing(matcher_online.is_set, lambda: progress(first), STALL_S,
                               "the matcher to come online")
        threads, epoch = start_cameras(case, broker.settings(), speed=SPEED, prefix="killed")
        wait_while_progressing(lambda: counts()[1] >= total // 4,
                               lambda: progress(first, threads), STALL_S,
                               "a quarter to be processed")
        first.send_signal(signal.SIGKILL)
        first.wait(10)
        killed_at = counts()[1]
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
        first_log.close()
    with open(tmp_path / "second.out", "w+") as out, open(tmp_path / "second.err", "w+") as err:
        second = subprocess.Popen(_matcher_command(case, broker, database), stdout=out,
                                  stderr=err, text=True, env=environment)
        try:
            wait_while_progressing(lambda: second.poll() is not None,
                                   lambda: progress(second, threads), STALL_S,
                                   "the restarted matcher to catch up and exit")
        finally:
            if second.poll() is None:
                second.kill()
                second.wait()
        stdout = (tmp_path / "second.out").read_text()
        stderr = (tmp_path / "second.err").read_text()
    for thread in threads:
        thread.join(30)
    watcher.close()
    assert second.returncode == 0, stderr
    summary = json.loads(stdout)
    assert killed_at < total, "the kill was not mid-stream"
    assert summary["processed"] == total
    with RuntimeStore(database, read_only=True) as store:
        assert_exactly_once(store, case, expected_tracks(case, epoch, SPEED))


# -- duplicates and bad input (both transports) -----------------------------------------


def _service(make_transport, tmp_path, cameras=("CVLab1", "CVLab2"), **policy):
    planes = scene_planes_small()
    store = RuntimeStore(tmp_path / "matcher.db")
    service = MatcherService(
        make_transport("matcher"), store, make_matcher("fusion", planes, list(cameras)), PLANE,
        list(cameras), policy=ValidationPolicy(**policy), window_s=0.2,
    )
    service.start()
    return service, store


def scene_planes_small():
    from cblrs.plane import PlaneSet, PlaneSpec

    return PlaneSet([PlaneSpec(PLANE, (0.0, 0.0), 20.0, 20.0)])


def good_message(camera: str, sequence: int, timestamp: float) -> CameraMessage:
    return CameraMessage(
        camera, sequence, timestamp, sequence,
        xyxy=np.array([[10.0, 20.0, 50.0, 120.0]]), confidence=np.array([0.9]),
        class_id=np.array([0]), colour=np.array([[1000, 2000, PLANE]]),
    )


def test_duplicate_deliveries_are_ignored(make_transport, tmp_path):
    service, store = _service(make_transport, tmp_path)
    camera = make_transport("camera", persistent=False)
    camera.connect()
    now = time.time()
    payloads = [encode_message(good_message("CVLab1", sequence, now + sequence), PLANE)
                for sequence in range(3)]
    topic = detections_topic(PLANE, "CVLab1")
    for payload in [*payloads, payloads[1], payloads[1], payloads[0]]:
        camera.publish(topic, payload)
    camera.flush(5)
    wait_until(lambda: store.counters().get("received", 0) == 6, 20, "six deliveries")
    service.close(flush=True)
    counters = store.counters()
    assert counters["accepted"] == 3
    assert counters["duplicates"] == 3
    assert counters["processed"] == 3
    assert len(store.messages()) == 3
    store.close()


def _document(camera="CVLab1", sequence=0, timestamp=None, **changes) -> dict:
    timestamp = time.time() if timestamp is None else timestamp
    document = json.loads(encode_message(good_message(camera, sequence, timestamp), PLANE))
    document.update(changes)
    return document


def _bytes(document: dict) -> bytes:
    return json.dumps(document).encode()


def _without(key: str) -> bytes:
    document = _document(sequence=3)
    del document[key]
    return _bytes(document)


def _with_detection(sequence: int, **changes) -> bytes:
    document = _document(sequence=sequence)
    document["detections"][0].update(changes)
    return _bytes(document)


BAD_INPUT = [
    # (label, topic camera, payload builder, expected reason)
    ("malformed json", "CVLab1", lambda: b'{"schema": "cblrs.detections/1", "camera": ',
     "malformed_json"),
    ("not an object", "CVLab1", lambda: b"[1, 2, 3]", "malformed_json"),
    ("wrong schema version", "CVLab1",
     lambda: _bytes(_document(sequence=1, schema="cblrs.detections/2")), "wrong_schema"),
    ("missing timestamp", "CVLab1", lambda: _without("timestamp"), "missing_field"),
    ("missing detections", "CVLab1", lambda: _without("detections"), "missing_field"),
    ("NaN timestamp", "CVLab1", lambda: _bytes(_document(sequence=4) | {"timestamp": math.nan}),
     "invalid_value"),
    ("infinite box", "CVLab1", lambda: _with_detection(5, box=[math.inf, 20.0, 50.0, 120.0]),
     "invalid_value"),
    ("oversized", "CVLab1",
     lambda: _bytes(_document(sequence=6, padding="x" * 5000)), "oversized"),
    ("colour out of range", "CVLab1",
     lambda: _with_detection(7, colour=[70000, 10, PLANE]), "colour_out_of_range"),
    ("unknown camera", "Stranger", lambda: _bytes(_document("Stranger", 8)), "unknown_camera"),
    ("camera differs from topic", "CVLab1",
     lambda: _bytes(_document("CVLab2", 9)), "topic_mismatch"),
    ("far in the past", "CVLab1",
     lambda: _bytes(_document(sequence=10, timestamp=time.time() - 3 * 86400)), "too_old"),
    ("far in the future", "CVLab1",
     lambda: _bytes(_document(sequence=11, timestamp=time.time() + 3600)), "in_future"),
]


def test_bad_input_is_rejected_counted_and_survived(make_transport, tmp_path):
    service, store = _service(make_transport, tmp_path, max_bytes=4096)
    sender = make_transport("sender", persistent=False)
    sender.connect()
    now = time.time()
    good = [encode_message(good_message("CVLab1", 100 + index, now + index), PLANE)
            for index in range(2)]
    sender.publish(detections_topic(PLANE, "CVLab1"), good[0])
    expected: dict[str, int] = {}
    for _, camera, build, reason in BAD_INPUT:
        sender.publish(detections_topic(PLANE, camera), build())
        expected[reason] = expected.get(reason, 0) + 1
    sender.publish(detections_topic(PLANE, "CVLab1"), good[1])
    sender.flush(5)
    total = len(BAD_INPUT) + 2
    wait_until(lambda: store.counters().get("received", 0) == total, 20, "every delivery")
    service.close(flush=True)
    stats = service.stats()
    assert stats["rejected_by_reason"] == expected
    assert stats["rejected"] == len(BAD_INPUT)
    assert stats["accepted"] == 2
    assert stats["processed"] == 2, "the matcher stopped tracking after bad input"
    assert not service.failed()
    store.close()
