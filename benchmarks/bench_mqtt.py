"""Throughput and latency of the MQTT runtime through Mosquitto on loopback (QoS 1).

Simulated cameras (one MQTT connection each, in a separate process) publish
``cblrs.detections/1`` messages to a local Mosquitto; one matcher service (this process:
validation, SQLite inbox, ordering, fusion tracker, SQLite tracks, track publishing) receives
them. Two runs per camera count:

* ``max``: every camera publishes its frames as fast as it can; figure: messages/s from the
  first publish to the last message stored (``received``) and tracked (``tracked``);
* ``paced``: every camera publishes one message per frame at ``--fps``; figures: p50/p99
  latency from the frame's capture time (its scheduled publish time, so publisher lag counts)
  to the matcher's receipt (stored in the inbox) and to the track output (group committed);
* ``transport``: as ``max`` but received by a bare subscriber that only acknowledges (the
  MQTT path alone: paho -> Mosquitto -> paho, QoS 1 both ways, manual acks).

Printed figures are medians over ``--repeats`` runs. Not a test: nothing is asserted.

Usage::

    python benchmarks/bench_mqtt.py                 # 1, 10, 50 cameras, 3 repeats
    python benchmarks/bench_mqtt.py --cameras 50 --repeats 5 --json
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.broker import MosquittoProcess, free_port, write_broker_config
from cblrs.runtime.matcher_service import MatcherService
from cblrs.runtime.store import RuntimeStore
from cblrs.runtime.topics import detections_topic, status_topic
from cblrs.runtime.transport import MqttSettings, MqttTransport
from cblrs.runtime.wire import ValidationPolicy, encode_message, encode_status

PLANE_ID = 1
PLANE = PlaneSpec(PLANE_ID, (0.0, 0.0), 40.0, 40.0)


def camera_names(count: int) -> list[str]:
    return [f"cam{index:03d}" for index in range(count)]


def frame_message(camera: str, index: int, frame: int, timestamp: float, people: int) -> bytes:
    """A message with ``people`` detections whose colours walk across the plane."""
    rng = np.random.default_rng(index * 100003 + frame)
    base = np.array(
        [[5.0 + 3 * person + 0.02 * frame, 5.0 + 2 * person] for person in range(people)]
    )
    world = base + rng.normal(0, 0.05, base.shape)
    colours, _ = PLANE.encode(world.reshape(-1, 2))
    message = CameraMessage(
        camera, frame, timestamp, frame,
        xyxy=np.tile([100.0, 100.0, 140.0, 220.0], (people, 1)),
        confidence=np.full(people, 0.9),
        class_id=np.zeros(people, np.int64),
        colour=colours.astype(np.int64).reshape(-1, 3),
    )
    return encode_message(message, PLANE_ID)


def publisher(port: int, cameras: int, frames: int, fps: float, paced: bool, people: int,
              results) -> None:
    """Child process: one MQTT connection per camera, frame-major publishing."""
    settings = MqttSettings(port=port, max_inflight=1000)
    names = camera_names(cameras)
    transports = [MqttTransport(f"bench-{name}", settings, persistent=False) for name in names]
    for transport in transports:
        transport.connect()
    for name, transport in zip(names, transports, strict=True):
        transport.publish(status_topic(PLANE_ID, name), encode_status(name, "online",
                          timestamp=time.time()), retain=True)
    epoch = time.time() - (0 if paced else frames / fps)
    payloads = None
    if not paced:  # as fast as possible: encode up front, measure the transport + matcher
        payloads = [[frame_message(name, index, frame, epoch + frame / fps, people)
                     for index, name in enumerate(names)] for frame in range(frames)]
    start = time.time() + 0.5
    upcoming = None
    for frame in range(frames):
        if paced:
            # Encode the frame ahead of its capture time, as each real camera would do in
            # parallel on its own device; the publish loop then only sends.
            upcoming = [frame_message(name, index, frame, start + frame / fps, people)
                        for index, name in enumerate(names)]
            delay = start + frame / fps - time.time()
            if delay > 0:
                time.sleep(delay)
        elif frame == 0:
            start = time.time()
        assert payloads is not None or upcoming is not None
        batch = payloads[frame] if payloads is not None else upcoming
        for name, transport, payload in zip(names, transports, batch, strict=True):
            transport.publish(detections_topic(PLANE_ID, name), payload)
    published = time.time()
    for name, transport in zip(names, transports, strict=True):
        transport.publish(status_topic(PLANE_ID, name), encode_status(name, "offline",
                          timestamp=time.time()), retain=True)
    flushed = all(transport.flush(60) for transport in transports)
    for transport in transports:
        transport.close(timeout=5)
    results.put({"start": start, "published": published, "flushed": flushed})


class Probe:
    """Observer of the matcher service: receipt and track-output times per message."""

    def __init__(self) -> None:
        self.receipt: list[float] = []
        self.tracked: list[float] = []
        self.last_stored = 0.0
        self.last_group = 0.0
        self.stored = 0

    def on_stored(self, messages, wall_time) -> None:
        self.receipt.extend(wall_time - message.timestamp for message in messages)
        self.last_stored = wall_time
        self.stored += len(messages)

    def on_group(self, timestamp, messages, tracks, wall_time) -> None:
        self.tracked.extend(wall_time - message.timestamp for message in messages)
        self.last_group = wall_time


class Counter:
    """A bare subscriber: acknowledge and count."""

    def __init__(self) -> None:
        self.count = 0
        self.last = 0.0

    def __call__(self, delivery) -> None:
        delivery.ack()
        self.count += 1
        self.last = time.time()


def run_transport_only(cameras: int, frames: int, fps: float, people: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="cblrs-bench-") as folder:
        port = free_port()
        files = write_broker_config(Path(folder) / "broker", [], [], port=port,
                                    allow_anonymous=True, viewer=False)
        broker = MosquittoProcess.from_files(files).start()
        try:
            counter = Counter()
            subscriber = MqttTransport("bench-subscriber", MqttSettings(port=port))
            subscriber.subscribe(f"cblrs/{PLANE_ID}/+/detections", counter)
            subscriber.connect()
            results: multiprocessing.Queue = multiprocessing.Queue()
            process = multiprocessing.Process(
                target=publisher, args=(port, cameras, frames, fps, False, people, results)
            )
            process.start()
            report = results.get(timeout=600)
            process.join(60)
            total = cameras * frames
            deadline = time.time() + 60
            while counter.count < total and time.time() < deadline:
                time.sleep(0.01)
            subscriber.close()
        finally:
            broker.stop()
    return {
        "cameras": cameras, "mode": "transport", "messages": total, "stored": counter.count,
        "late": 0, "rejected": 0,
        "publish_per_s": total / max(report["published"] - report["start"], 1e-9),
        "received_per_s": total / (counter.last - report["start"]),
        "tracked_per_s": math.nan,
        "receipt_p50_ms": math.nan, "receipt_p99_ms": math.nan,
        "track_p50_ms": math.nan, "track_p99_ms": math.nan,
    }


def run_once(cameras: int, frames: int, fps: float, paced: bool, people: int,
             matcher_name: str) -> dict:
    with tempfile.TemporaryDirectory(prefix="cblrs-bench-") as folder:
        port = free_port()
        files = write_broker_config(Path(folder) / "broker", [], [], port=port,
                                    allow_anonymous=True, viewer=False)
        broker = MosquittoProcess.from_files(files).start()
        try:
            names = camera_names(cameras)
            store = RuntimeStore(Path(folder) / "matcher.db")
            probe = Probe()
            service = MatcherService(
                MqttTransport("bench-matcher", MqttSettings(port=port), persistent=True),
                store, make_matcher(matcher_name, PlaneSet([PLANE]), names), PLANE_ID, names,
                policy=ValidationPolicy(max_future_s=3600.0), window_s=2.0, observer=probe,
            )
            service.start()
            results: multiprocessing.Queue = multiprocessing.Queue()
            process = multiprocessing.Process(
                target=publisher, args=(port, cameras, frames, fps, paced, people, results)
            )
            process.start()
            report = results.get(timeout=600)
            process.join(60)
            total = cameras * frames
            deadline = time.time() + 120
            while (probe.stored < total or not service.drained()) and time.time() < deadline:
                time.sleep(0.01)
            service.close(flush=True)
            stats = service.stats()
            store.close()
        finally:
            broker.stop()
    span_received = probe.last_stored - report["start"]
    span_tracked = probe.last_group - report["start"]
    if not paced:  # capture times are synthetic here: latencies would mean nothing
        probe.receipt = probe.tracked = [math.nan]
    return {
        "cameras": cameras,
        "mode": "paced" if paced else "max",
        "messages": total,
        "stored": probe.stored,
        "late": stats["late"],
        "rejected": stats["rejected"],
        "publish_per_s": total / max(report["published"] - report["start"], 1e-9),
        "received_per_s": total / span_received,
        "tracked_per_s": total / span_tracked,
        "receipt_p50_ms": 1000 * float(np.percentile(probe.receipt, 50)),
        "receipt_p99_ms": 1000 * float(np.percentile(probe.receipt, 99)),
        "track_p50_ms": 1000 * float(np.percentile(probe.tracked, 50)),
        "track_p99_ms": 1000 * float(np.percentile(probe.tracked, 99)),
    }


def median_of(runs: list[dict]) -> dict:
    merged = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, float):
            merged[key] = statistics.median(run[key] for run in runs)
    merged["repeats"] = len(runs)
    return merged


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cameras", type=int, nargs="+", default=[1, 10, 50])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-messages", type=int, default=20000,
                        help="messages per max-throughput run (split over the cameras)")
    parser.add_argument("--paced-seconds", type=float, default=5.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--people", type=int, default=2, help="detections per message")
    parser.add_argument("--matcher", default="fusion")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    rows = []
    for cameras in args.cameras:
        for mode in ("transport", "max", "paced"):
            paced = mode == "paced"
            frames = (int(args.paced_seconds * args.fps) if paced
                      else max(1, args.max_messages // cameras))
            if mode == "transport":
                runs = [run_transport_only(cameras, frames, args.fps, args.people)
                        for _ in range(args.repeats)]
            else:
                runs = [run_once(cameras, frames, args.fps, paced, args.people, args.matcher)
                        for _ in range(args.repeats)]
            row = median_of(runs)
            rows.append(row)
            if not args.json:
                print(
                    f"{cameras:3d} cameras {row['mode']:9s} {row['messages']:6d} msgs: "
                    f"received {row['received_per_s']:8.0f}/s tracked {row['tracked_per_s']:8.0f}/s"
                    f" | receipt p50 {row['receipt_p50_ms']:7.2f} p99 {row['receipt_p99_ms']:7.2f}"
                    f" ms | track p50 {row['track_p50_ms']:7.2f} p99 {row['track_p99_ms']:7.2f} ms"
                    f" | late {row['late']} rejected {row['rejected']}",
                    flush=True,
                )
    if args.json:
        document = {"python": sys.version.split()[0], "cpus": multiprocessing.cpu_count(),
                    "results": rows}
        print(json.dumps(document, indent=2, default=lambda value: None).replace("NaN", "null"))
    return 0


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    sys.exit(main())
