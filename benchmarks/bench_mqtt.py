"""Throughput and latency of the MQTT runtime through Mosquitto on loopback (QoS 1).

Simulated cameras publish ``cblrs.detections/1`` messages (``--people`` detections each) to a
local Mosquitto, one MQTT connection per camera, from *other processes* than the receiver, so
publishers never share the receiver's interpreter (GIL):

* ``--publisher mosquitto_pub`` (default): one ``mosquitto_pub -l -q 1`` process (C) per
  camera, fed its payload lines through a pipe by a feeder process;
* ``--publisher paho``: one Python process holding one paho connection per camera.

Receivers (one at a time, each in this process):

* ``broker``: ``mosquitto_sub -q 1`` (C): the broker's own ceiling on this machine;
* ``paho``: a bare paho-mqtt 2.x client (MQTT 5, manual acks) that only acknowledges: the
  ceiling of any Python paho subscriber here;
* ``transport``: :class:`~cblrs.runtime.transport.MqttTransport` with a handler that only
  acknowledges (the runtime's transport wrapper);
* ``matcher``: the full :class:`~cblrs.runtime.matcher_service.MatcherService`: validation,
  SQLite inbox (ack after commit), ordering in this process; the fusion tracker in the
  service's tracker process (one transaction per group batch, track rows in SQLite); track
  updates published from this process. Like ``cblrs matcher``, the run calls
  ``gc.freeze()`` before starting the service.

Rates:

* ``max``: every camera publishes its frames as fast as it can; figure: messages/s from the
  first publish to the last message received (matcher: stored, and tracked);
* ``paced``: every camera publishes one message per frame at ``--fps`` (50 cameras x 30 fps
  = 1500 messages/s); figures: p50/p99 latency from the frame's capture time (its scheduled
  publish time, so publisher lag counts) to the receipt (paho: the callback; matcher: stored
  in the inbox and acknowledged), to the track output (matcher: the group committed by the
  tracker process and its update handed to the transport, in the service's process), and —
  the figure a user sees — to the track update's arrival at a *separate subscriber process*
  (a paho client on ``cblrs/<plane>/tracks``, one sample per update, i.e. per frame).

``--nagle`` leaves Nagle's algorithm on (no ``TCP_NODELAY`` on the matcher's, the broker's and
the subscriber's sockets), as cblrs did before issue 10: small packets (a track update, an
acknowledgement) then wait for the previous one's TCP acknowledgement.

Printed figures are medians over ``--repeats`` runs, with the machine (CPU, cores, load
average at start and end). Not a test: nothing is asserted.

Usage::

    python benchmarks/bench_mqtt.py                 # 1, 10, 50 cameras, 3 repeats
    python benchmarks/bench_mqtt.py --cameras 50 --repeats 5 --json
    python benchmarks/bench_mqtt.py --stages        # per-step costs in-process, no broker
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import multiprocessing
import os
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from importlib import metadata
from pathlib import Path

import msgspec
import numpy as np

from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.broker import MosquittoProcess, free_port, write_broker_config
from cblrs.runtime.matcher_service import MatcherService
from cblrs.runtime.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.store import InboxEntry, RuntimeStore
from cblrs.runtime.topics import detections_filter, detections_topic, tracks_topic
from cblrs.runtime.wire import ValidationPolicy, encode_message

PLANE_ID = 1
PLANE = PlaneSpec(PLANE_ID, (0.0, 0.0), 40.0, 40.0)
RECEIVERS = ("broker", "paho", "transport", "matcher")
DEFAULT_RUNS = ("broker/max", "paho/max", "transport/max", "matcher/max", "paho/paced",
                "matcher/paced")


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


# --------------------------------------------------------------------------- publishers


def publisher(kind: str, port: int, cameras: int, frames: int, fps: float, paced: bool,
              people: int, results) -> None:
    """Child process: simulate ``cameras`` cameras; put timing facts on ``results``."""
    try:
        if kind == "mosquitto_pub":
            report = _publish_with_mosquitto_pub(port, cameras, frames, fps, paced, people)
        else:
            report = _publish_with_paho(port, cameras, frames, fps, paced, people)
    except BaseException as error:
        results.put({"error": repr(error)})
        raise
    results.put(report)


def _frames(names: list[str], frames: int, fps: float, epoch: float, people: int):
    return [[frame_message(name, index, frame, epoch + frame / fps, people)
             for index, name in enumerate(names)] for frame in range(frames)]


def _publish_with_mosquitto_pub(port: int, cameras: int, frames: int, fps: float, paced: bool,
                                people: int) -> dict:
    names = camera_names(cameras)
    processes = [
        subprocess.Popen(
            ["mosquitto_pub", "-h", "127.0.0.1", "-p", str(port), "-q", "1", "-M", "1000",
             "-i", f"bench-{name}", "-t", detections_topic(PLANE_ID, name), "-l"],
            stdin=subprocess.PIPE, bufsize=0,
        )
        for name in names
    ]
    if not paced:  # as fast as possible: encode up front, then measure transport + receiver
        epoch = time.time() - frames / fps
        streams = [b"".join(payload + b"\n" for payload in column)
                   for column in zip(*_frames(names, frames, fps, epoch, people), strict=True)]
    time.sleep(1.0 + 0.02 * cameras)  # every mosquitto_pub connected
    start = time.time()
    if paced:
        start += 0.2
        upcoming = [frame_message(name, index, 0, start, people)
                    for index, name in enumerate(names)]
        for frame in range(frames):
            capture = start + frame / fps
            delay = capture - time.time()
            if delay > 0:
                time.sleep(delay)
            for process, payload in zip(processes, upcoming, strict=True):
                assert process.stdin is not None
                process.stdin.write(payload + b"\n")
            # Encode the next frame ahead of its capture time, as each real camera would do
            # on its own device; the loop above then only sends.
            upcoming = [frame_message(name, index, frame + 1, start + (frame + 1) / fps, people)
                        for index, name in enumerate(names)]
    else:
        def feed(process: subprocess.Popen, stream: bytes) -> None:
            assert process.stdin is not None
            process.stdin.write(stream)
            process.stdin.close()

        threads = [threading.Thread(target=feed, args=pair) for pair in
                   zip(processes, streams, strict=True)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    published = time.time()
    for process in processes:
        if process.stdin is not None and not process.stdin.closed:
            process.stdin.close()
    flushed = all(process.wait(120) == 0 for process in processes)
    return {"start": start, "published": published, "flushed": flushed}


def _publish_with_paho(port: int, cameras: int, frames: int, fps: float, paced: bool,
                       people: int) -> dict:
    settings = MqttSettings(port=port, max_inflight=1000)
    names = camera_names(cameras)
    transports = [MqttTransport(f"bench-{name}", settings, persistent=False) for name in names]
    for transport in transports:
        transport.connect()
    payloads = None
    if not paced:
        payloads = _frames(names, frames, fps, time.time() - frames / fps, people)
    start = time.time() + (0.2 if paced else 0.0)
    upcoming = None
    for frame in range(frames):
        if paced:
            upcoming = [frame_message(name, index, frame, start + frame / fps, people)
                        for index, name in enumerate(names)]
            delay = start + frame / fps - time.time()
            if delay > 0:
                time.sleep(delay)
        batch = payloads[frame] if payloads is not None else upcoming
        assert batch is not None
        for name, transport, payload in zip(names, transports, batch, strict=True):
            transport.publish(detections_topic(PLANE_ID, name), payload)
    published = time.time()
    flushed = all(transport.flush(120) for transport in transports)
    for transport in transports:
        transport.close(timeout=5)
    return {"start": start, "published": published, "flushed": flushed}


# --------------------------------------------------------------------------- receivers


class _Timestamp(msgspec.Struct):
    timestamp: float


_timestamp_decoder = msgspec.json.Decoder(_Timestamp)


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


class _Receiver:
    """Counts deliveries (and, paced, the capture-to-callback latency)."""

    def __init__(self, total: int, paced: bool) -> None:
        self.total = total
        self.paced = paced
        self.count = 0
        self.last = 0.0
        self.receipt: list[float] = []
        self.done = threading.Event()

    def received(self, payload: bytes) -> None:
        now = time.time()
        if self.paced:
            self.receipt.append(now - _timestamp_decoder.decode(payload).timestamp)
        self.count += 1
        self.last = now
        if self.count >= self.total:
            self.done.set()


def _start_paho(port: int, receiver: _Receiver):
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    client = mqtt.Client(callback_api_version=CallbackAPIVersion.VERSION2,
                         client_id="bench-paho", protocol=mqtt.MQTTv5)
    client.manual_ack_set(True)
    subscribed = threading.Event()

    def on_message(client, userdata, message) -> None:
        client.ack(message.mid, message.qos)
        receiver.received(message.payload)

    client.on_message = on_message
    client.on_subscribe = lambda *args: subscribed.set()
    client.connect("127.0.0.1", port)
    client.subscribe(detections_filter(PLANE_ID), qos=1)
    client.loop_start()
    if not subscribed.wait(10):
        raise RuntimeError("bare paho subscriber got no SUBACK")
    return client


class _TrackTimes(msgspec.Struct):
    timestamp: float


class _TrackUpdate(msgspec.Struct):
    tracks: list[_TrackTimes]


_update_decoder = msgspec.json.Decoder(_TrackUpdate)


def track_subscriber(port: int, nagle: bool, ready, stop, results) -> None:
    """Child process: a paho client on the tracks topic; capture -> arrival latency of each
    track update (its rows carry the frame's capture time)."""
    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    latencies: list[float] = []
    client = mqtt.Client(callback_api_version=CallbackAPIVersion.VERSION2,
                         client_id="bench-tracks", protocol=mqtt.MQTTv5)
    if not nagle:
        client.on_socket_open = lambda c, u, sock: sock.setsockopt(
            socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def on_message(client, userdata, message) -> None:
        now = time.time()
        update = _update_decoder.decode(message.payload)
        if update.tracks:
            latencies.append(now - update.tracks[0].timestamp)

    client.on_message = on_message
    client.on_subscribe = lambda *args: ready.set()
    client.connect("127.0.0.1", port)
    client.subscribe(tracks_topic(PLANE_ID), qos=1)
    client.loop_start()
    stop.wait(1200)
    time.sleep(0.2)
    client.loop_stop()
    results.put(latencies)


def run_once(receiver_kind: str, publisher_kind: str, cameras: int, frames: int, fps: float,
             paced: bool, people: int, matcher_name: str, nagle: bool = False) -> dict:
    total = cameras * frames
    with tempfile.TemporaryDirectory(prefix="cblrs-bench-") as folder:
        port = free_port()
        files = write_broker_config(Path(folder) / "broker", [], [], port=port,
                                    allow_anonymous=True, viewer=False, persistence=False,
                                    run_as="root" if os.geteuid() == 0 else None)
        if nagle:
            files.config.write_text(files.config.read_text().replace("set_tcp_nodelay true\n",
                                                                     ""))
        broker = MosquittoProcess.from_files(files).start()
        subscriber_process = None
        subscriber_latencies: list[float] = []
        subscriber_results: multiprocessing.Queue = multiprocessing.Queue()
        subscriber_stop = multiprocessing.Event()
        receiver = _Receiver(total, paced)
        probe = Probe()
        service = store = client = transport = subscriber = None
        try:
            if receiver_kind == "broker":
                subscriber = subprocess.Popen(
                    ["mosquitto_sub", "-h", "127.0.0.1", "-p", str(port), "-q", "1",
                     "-i", "bench-sub", "-t", detections_filter(PLANE_ID), "-C", str(total)],
                    stdout=subprocess.DEVNULL,
                )
                time.sleep(0.5)
            elif receiver_kind == "paho":
                client = _start_paho(port, receiver)
            elif receiver_kind == "transport":
                transport = MqttTransport("bench-transport", MqttSettings(port=port),
                                          persistent=False)

                def handler(delivery) -> None:
                    delivery.ack()
                    receiver.received(delivery.payload)

                transport.subscribe(detections_filter(PLANE_ID), handler)
                transport.connect()
            else:
                names = camera_names(cameras)
                store = RuntimeStore(Path(folder) / "matcher.db")
                service = MatcherService(
                    MqttTransport("bench-matcher",
                                  MqttSettings(port=port, tcp_nodelay=not nagle),
                                  persistent=True),
                    store, make_matcher(matcher_name, PlaneSet([PLANE]), names), PLANE_ID,
                    names, policy=ValidationPolicy(max_future_s=3600.0), window_s=2.0,
                    observer=probe,
                )
                if paced:
                    ready = multiprocessing.Event()
                    subscriber_process = multiprocessing.Process(
                        target=track_subscriber,
                        args=(port, nagle, ready, subscriber_stop, subscriber_results),
                    )
                    subscriber_process.start()
                    if not ready.wait(30):
                        raise RuntimeError("the tracks subscriber did not subscribe")
                gc.freeze()  # as cblrs matcher does before starting its service
                service.start()
            results: multiprocessing.Queue = multiprocessing.Queue()
            process = multiprocessing.Process(
                target=publisher,
                args=(publisher_kind, port, cameras, frames, fps, paced, people, results),
            )
            process.start()
            report = results.get(timeout=900)
            process.join(60)
            if "error" in report:
                raise RuntimeError(f"publisher failed: {report['error']}")
            deadline = time.time() + 120
            if subscriber is not None:
                subscriber.wait(120)
                receiver.count, receiver.last = total, time.time()
            elif service is not None:
                while (probe.stored < total or not service.drained()) and time.time() < deadline:
                    time.sleep(0.005)
                receiver.count, receiver.last = probe.stored, probe.last_stored
                service.close(flush=True)
                stats = service.stats()
                if subscriber_process is not None:
                    subscriber_stop.set()
                    subscriber_latencies = subscriber_results.get(timeout=60)
                    subscriber_process.join(30)
            else:
                receiver.done.wait(max(0.0, deadline - time.time()))
        finally:
            if subscriber is not None and subscriber.poll() is None:
                subscriber.kill()
            if client is not None:
                client.disconnect()
                client.loop_stop()
            if transport is not None:
                transport.close()
            if store is not None:
                store.close()
            broker.stop()
    row = {
        "receiver": receiver_kind, "rate": "paced" if paced else "max", "cameras": cameras,
        "messages": total, "received": receiver.count, "flushed": report["flushed"],
        "publish_per_s": total / max(report["published"] - report["start"], 1e-9),
        "received_per_s": receiver.count / max(receiver.last - report["start"], 1e-9),
        "tracked_per_s": math.nan, "late": 0, "rejected": 0,
        "receipt_p50_ms": math.nan, "receipt_p99_ms": math.nan,
        "track_p50_ms": math.nan, "track_p99_ms": math.nan,
        "subscriber_p50_ms": math.nan, "subscriber_p99_ms": math.nan, "nagle": nagle,
    }
    if paced and receiver.receipt:
        row["receipt_p50_ms"] = 1000 * float(np.percentile(receiver.receipt, 50))
        row["receipt_p99_ms"] = 1000 * float(np.percentile(receiver.receipt, 99))
    if service is not None:
        row["tracked_per_s"] = total / max(probe.last_group - report["start"], 1e-9)
        row["late"], row["rejected"] = stats["late"], stats["rejected"]
        if paced:  # in max runs capture times are synthetic: latencies would mean nothing
            row["receipt_p50_ms"] = 1000 * float(np.percentile(probe.receipt, 50))
            row["receipt_p99_ms"] = 1000 * float(np.percentile(probe.receipt, 99))
            row["track_p50_ms"] = 1000 * float(np.percentile(probe.tracked, 50))
            row["track_p99_ms"] = 1000 * float(np.percentile(probe.tracked, 99))
            if subscriber_latencies:
                row["subscriber_p50_ms"] = 1000 * float(np.percentile(subscriber_latencies, 50))
                row["subscriber_p99_ms"] = 1000 * float(np.percentile(subscriber_latencies, 99))
                row["subscriber_updates"] = len(subscriber_latencies)
    return row


def median_of(runs: list[dict]) -> dict:
    merged = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, float):
            merged[key] = statistics.median(run[key] for run in runs)
    merged["received"] = min(run["received"] for run in runs)
    merged["flushed"] = all(run["flushed"] for run in runs)
    merged["repeats"] = len(runs)
    return merged


# --------------------------------------------------------------------------- stages


def _best_seconds(function, number: int, repeats: int = 5) -> float:
    """Best mean time of ``function`` over ``repeats`` rounds of ``number`` calls, seconds."""
    best = math.inf
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(number):
            function()
        best = min(best, (time.perf_counter() - started) / number)
    return best


def measure_stages(cameras: int, people: int, matcher_name: str, frames: int = 90) -> dict:
    """In-process cost of each step a message or group takes in the matcher, no MQTT.

    Receiver (service process): decode and validate a payload into its inbox entry, insert
    entries (one transaction per frame of all cameras). Tracker process: rebuild the
    messages of a group from their entries and update the matcher; commit a group.
    """
    names = camera_names(cameras)
    policy = ValidationPolicy(known_cameras=frozenset(names), max_future_s=3600.0)
    epoch = time.time()
    payloads = _frames(names, frames, 30.0, epoch, people)
    topic_camera = names[-1]
    payload = payloads[0][-1]
    decode = _best_seconds(
        lambda: InboxEntry.from_wire(policy.decode_wire(
            payload, topic_camera=topic_camera, now=epoch, topic_plane=PLANE_ID)), 2000)
    groups = [[InboxEntry.from_wire(policy.decode_wire(item, now=epoch)) for item in group]
              for group in payloads]
    matcher = make_matcher(matcher_name, PlaneSet([PLANE]), names)
    updates = []
    outputs = []
    for frame, group in enumerate(groups):
        started = time.perf_counter()
        outputs.append(matcher.update(epoch + frame / 30.0, [entry.message() for entry in group]))
        updates.append(time.perf_counter() - started)
    steady = updates[frames // 3:]  # after the tracks are born
    with tempfile.TemporaryDirectory(prefix="cblrs-bench-") as folder:
        store = RuntimeStore(Path(folder) / "stages.db")
        rows = [(entry, "pending", epoch) for group in groups for entry in group]
        started = time.perf_counter()
        for start in range(0, len(rows), cameras):
            store.insert_messages(rows[start:start + cameras])
        insert = (time.perf_counter() - started) / len(rows)
        started = time.perf_counter()
        for frame, group in enumerate(groups):
            store.commit_group([(m.camera_id, m.sequence) for m in group], outputs[frame],
                               matcher.get_state(), epoch + frame / 30.0, {"groups": 1})
        commit = (time.perf_counter() - started) / frames
        stored_bytes = store.used_bytes() / len(rows)  # inbox + track rows, per message
        store.close()
    return {
        "cameras": cameras, "people": people, "matcher": matcher_name,
        "decode_us_per_message": 1e6 * decode,
        "insert_us_per_message": 1e6 * insert,
        "update_ms_per_group": 1e3 * statistics.median(steady),
        "update_us_per_message": 1e6 * statistics.median(steady) / cameras,
        "update_worst_ms": 1e3 * max(updates),
        "commit_ms_per_group": 1e3 * commit,
        "database_bytes_per_message": stored_bytes,
    }


# --------------------------------------------------------------------------- machine


def machine() -> dict:
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = {}
    for package in ("paho-mqtt", "msgspec", "numpy"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    try:
        mosquitto = subprocess.run(["mosquitto", "-h"], capture_output=True, text=True,
                                   timeout=10).stdout.splitlines()[0]
    except (OSError, IndexError, subprocess.SubprocessError):
        mosquitto = None
    return {"cpu": model, "cores": os.cpu_count(), "python": platform.python_version(),
            "mosquitto": mosquitto, **versions}


def _format(value: float, width: int = 7, digits: int = 1) -> str:
    return " " * (width - 1) + "-" if math.isnan(value) else f"{value:{width}.{digits}f}"


def markdown_table(info: dict, rows: list[dict], args: argparse.Namespace) -> str:
    """The results as a markdown table with the machine and settings above it."""

    def cell(value: float, digits: int = 1) -> str:
        return "–" if math.isnan(value) else f"{value:.{digits}f}"

    def pair(first: float, second: float) -> str:
        return "–" if math.isnan(first) else f"{cell(first)} / {cell(second)}"

    lines = [
        f"QoS 1 on loopback, {args.people} detections per message, {args.fps:g} fps when paced, "
        f"{args.matcher} matcher; publishers: {args.publisher} (one connection per camera, "
        f"other processes). {info['cpu']}, {info['cores']} cores, Python {info['python']}, "
        f"{info['mosquitto']}, paho-mqtt {info['paho-mqtt']}; "
        + ("Nagle's algorithm on (no TCP_NODELAY); " if args.nagle else "TCP_NODELAY on; ")
        + "load average "
        f"{info['load_start'][0]:.2f} at start, {info['load_end'][0]:.2f} at end (a shared "
        f"machine); medians of {args.repeats} runs.",
        "",
        "| cameras | receiver | rate | received msg/s | tracked msg/s "
        "| receipt p50 / p99 ms | track output p50 / p99 ms "
        "| **tracks at a subscriber** p50 / p99 ms | lost |",
        "|---:|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(
            f"| {row['cameras']} | {row['receiver']} | {row['rate']} "
            f"| {row['received_per_s']:.0f} | {cell(row['tracked_per_s'], 0)} "
            f"| {pair(row['receipt_p50_ms'], row['receipt_p99_ms'])} "
            f"| {pair(row['track_p50_ms'], row['track_p99_ms'])} "
            f"| {pair(row['subscriber_p50_ms'], row['subscriber_p99_ms'])} "
            f"| {row['messages'] - row['received']} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cameras", type=int, nargs="+", default=[1, 10, 50])
    parser.add_argument("--runs", nargs="+", default=list(DEFAULT_RUNS),
                        help="receiver/rate pairs, receiver in broker, paho, transport, "
                        "matcher and rate in max, paced")
    parser.add_argument("--publisher", choices=("mosquitto_pub", "paho"),
                        default="mosquitto_pub" if shutil.which("mosquitto_pub") else "paho")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-messages", type=int, default=20000,
                        help="messages per max-throughput run (split over the cameras)")
    parser.add_argument("--paced-seconds", type=float, default=5.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--people", type=int, default=2, help="detections per message")
    parser.add_argument("--matcher", default="fusion")
    parser.add_argument("--nagle", action="store_true",
                        help="leave Nagle's algorithm on (no TCP_NODELAY), as before issue 10")
    parser.add_argument("--stages", action="store_true",
                        help="only time each matcher step in-process (no broker) and exit")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--markdown", action="store_true",
                        help="print a markdown table (for docs/results/bench_mqtt.md)")
    args = parser.parse_args(argv)
    if args.stages:
        stage_rows = [measure_stages(cameras, args.people, args.matcher)
                      for cameras in args.cameras]
        if args.json:
            print(json.dumps({"machine": machine(), "stages": stage_rows}, indent=2))
        for row in stage_rows if not args.json else []:
            print(f"{row['cameras']:3d} cameras: decode {row['decode_us_per_message']:5.1f} us/msg"
                  f", inbox insert {row['insert_us_per_message']:5.1f} us/msg, {args.matcher} "
                  f"update {row['update_ms_per_group']:5.2f} ms/group "
                  f"({row['update_us_per_message']:5.0f} us/msg, worst frame "
                  f"{row['update_worst_ms']:5.1f} ms), commit "
                  f"{row['commit_ms_per_group']:5.2f} ms/group; database "
                  f"{row['database_bytes_per_message']:.0f} bytes/message")
        return 0
    for run in args.runs:
        receiver, _, rate = run.partition("/")
        if receiver not in RECEIVERS or rate not in ("max", "paced"):
            parser.error(f"bad run {run!r}: expected <{'|'.join(RECEIVERS)}>/<max|paced>")
        if receiver == "broker" and rate == "paced":
            parser.error("the broker receiver (mosquitto_sub) measures max throughput only")
    info = machine()
    info["load_start"] = list(os.getloadavg())
    if not (args.json or args.markdown):
        print(f"{info['cpu']}, {info['cores']} cores, Python {info['python']}, "
              f"{info['mosquitto']}, paho-mqtt {info['paho-mqtt']}; publisher: "
              f"{args.publisher}; load average {info['load_start'][0]:.2f}", flush=True)
        print(f"{'cams':>4s} {'receiver':9s} {'rate':5s} {'msgs':>6s} {'recv/s':>8s} "
              f"{'track/s':>8s} | {'receipt p50':>11s} {'p99 ms':>7s} | {'track p50':>9s} "
              f"{'p99 ms':>7s} | {'subscr p50':>10s} {'p99 ms':>7s} | lost late", flush=True)
    rows = []
    for cameras in args.cameras:
        for run in args.runs:
            receiver, _, rate = run.partition("/")
            paced = rate == "paced"
            frames = (int(args.paced_seconds * args.fps) if paced
                      else max(1, args.max_messages // cameras))
            runs = [run_once(receiver, args.publisher, cameras, frames, args.fps, paced,
                             args.people, args.matcher, args.nagle)
                    for _ in range(args.repeats)]
            row = median_of(runs)
            row["runs"] = runs
            rows.append(row)
            if not (args.json or args.markdown):
                print(
                    f"{cameras:4d} {receiver:9s} {rate:5s} {row['messages']:6d} "
                    f"{row['received_per_s']:8.0f} {_format(row['tracked_per_s'], 8, 0)} | "
                    f"{_format(row['receipt_p50_ms'], 11)} {_format(row['receipt_p99_ms'])} | "
                    f"{_format(row['track_p50_ms'], 9)} {_format(row['track_p99_ms'])} | "
                    f"{_format(row['subscriber_p50_ms'], 10)} "
                    f"{_format(row['subscriber_p99_ms'])} | "
                    f"{row['messages'] - row['received']:4d} {row['late']:4d}",
                    flush=True,
                )
    info["load_end"] = list(os.getloadavg())
    if args.markdown:
        print(markdown_table(info, rows, args))
    elif args.json:
        document = {"machine": info, "publisher": args.publisher, "repeats": args.repeats,
                    "fps": args.fps, "people": args.people, "matcher": args.matcher,
                    "results": rows}
        print(json.dumps(document, indent=2).replace("NaN", "null"))
    else:
        print(f"load average at end {info['load_end'][0]:.2f} (1 min), "
              f"{info['load_end'][1]:.2f} (5 min); medians over {args.repeats} runs")
    return 0


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    sys.exit(main())
