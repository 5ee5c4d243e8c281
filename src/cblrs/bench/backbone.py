"""``cblrs bench backbone``: Mosquitto, NATS (one node) and NATS R3 (three nodes) side by side.

For each backbone, camera count and rate, one run starts its own servers on loopback ports
and a full :class:`~cblrs.runtime.matcher.matcher_service.MatcherService` in this process (MQTT
transport on Mosquitto; the NATS transport with the plane's durable consumer and lease on
NATS), then simulated cameras publish ``cblrs.detections/1`` messages (2 detections each).

* Publishers: one ``mosquitto_pub -q 1`` process per camera (other processes than the
  matcher), MQTT 5 to Mosquitto and MQTT 3.1.1 to the NATS server's MQTT listener (node 1 of
  the cluster): cameras unchanged, as a deployment would run them. ``nats-native`` and
  ``nats-r3-native`` publish with cblrs's own NATS transport instead (JetStream publishes
  acknowledged by the stream, ``publish_window`` of them in flight per camera), one
  transport per camera in up to four publisher processes.
* ``max``: every camera publishes as fast as it can; figure: messages received, stored in
  SQLite and acknowledged per second (first publish to last stored), and tracked per second.
* ``paced``: every camera publishes one message per frame at 30 fps; figure: capture ->
  track update latency p50/p99 **at a subscriber of the tracks** (a separate process
  subscribed to ``cblrs/<plane>/tracks``: paho on Mosquitto, nats-py on NATS), one sample per
  update (a timestamp group).

Not a test: nothing is asserted; ``lost`` is messages published minus messages stored.
"""

from __future__ import annotations

import asyncio
import gc
import math
import multiprocessing
import os
import statistics
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from cblrs.bench.machine import describe_machine, machine_info
from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.broker.mosquitto_config import MosquittoProcess, free_port, write_broker_config
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.transport.nats_transport import LeaseSettings, NatsSettings, NatsTransport
from cblrs.runtime.transport.topics import detections_topic
from cblrs.runtime.wire import ValidationPolicy, encode_message

PLANE_ID = 1
BACKBONES = ("mosquitto", "nats", "nats-r3", "nats-native", "nats-r3-native")
PUBLISHER_PROCESSES = 4


def _camera_names(count: int) -> list[str]:
    return [f"cam{index:03d}" for index in range(count)]


def _payload(camera: str, index: int, frame: int, timestamp: float, people: int) -> bytes:
    plane = PlaneSpec(PLANE_ID, (0.0, 0.0), 40.0, 40.0)
    rng = np.random.default_rng(index * 100003 + frame)
    world = np.array([[5.0 + 3 * p + 0.02 * frame, 5.0 + 2 * p] for p in range(people)])
    colours, _ = plane.encode(world + rng.normal(0, 0.05, world.shape))
    message = CameraMessage(
        camera, frame, timestamp, frame, xyxy=np.tile([100.0, 100.0, 140.0, 220.0], (people, 1)),
        confidence=np.full(people, 0.9), class_id=np.zeros(people, np.int64),
        colour=colours.astype(np.int64).reshape(-1, 3),
    )
    return encode_message(message, PLANE_ID)


# --------------------------------------------------------------------------- publishers


def _publish(port: int, mqtt_version: str, cameras: int, frames: int, fps: float, paced: bool,
             people: int, results: Any) -> None:
    """Child process: one mosquitto_pub per camera; reports the first publish time."""

    names = _camera_names(cameras)
    processes = [
        subprocess.Popen(
            ["mosquitto_pub", "-h", "127.0.0.1", "-p", str(port), "-q", "1", "-M", "1000",
             "-V", mqtt_version, "-i", f"bench-{name}", "-t", detections_topic(PLANE_ID, name),
             "-l"],
            stdin=subprocess.PIPE, bufsize=0,
        )
        for name in names
    ]
    streams = None
    if not paced:
        epoch = time.time() - frames / fps
        streams = [b"".join(_payload(name, index, frame, epoch + frame / fps, people) + b"\n"
                            for frame in range(frames)) for index, name in enumerate(names)]
    time.sleep(1.0 + 0.02 * cameras)  # every mosquitto_pub connected
    start = time.time()
    if streams is not None:
        def feed(process: subprocess.Popen, stream: bytes) -> None:
            assert process.stdin is not None
            process.stdin.write(stream)
            process.stdin.close()

        threads = [threading.Thread(target=feed, args=pair)
                   for pair in zip(processes, streams, strict=True)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    else:
        start += 0.2
        upcoming = [_payload(name, index, 0, start, people) for index, name in enumerate(names)]
        for frame in range(frames):
            delay = start + frame / fps - time.time()
            if delay > 0:
                time.sleep(delay)
            for process, payload in zip(processes, upcoming, strict=True):
                assert process.stdin is not None
                process.stdin.write(payload + b"\n")
            upcoming = [_payload(name, index, frame + 1, start + (frame + 1) / fps, people)
                        for index, name in enumerate(names)]
        for process in processes:
            assert process.stdin is not None
            process.stdin.close()
    flushed = all(process.wait(300) == 0 for process in processes)
    results.put({"start": start, "flushed": flushed})


def _publish_nats(url: str, names: list[str], frames: int, fps: float, paced: bool,
                  people: int, window: int, start_at: float, results: Any) -> None:
    """Child process: one NATS transport per camera of ``names``, JetStream publishes in
    order with ``window`` awaiting acknowledgement; reports whether all were acknowledged."""
    transports = [NatsTransport(f"bench-{name}", NatsSettings.from_url(
        url, publish_window=window, publish_timeout_s=10.0)) for name in names]
    for transport in transports:
        transport.connect()
    topics = [detections_topic(PLANE_ID, name) for name in names]
    if not paced:
        epoch = time.time() - frames / fps
        streams = [[_payload(name, index, frame, epoch + frame / fps, people)
                    for frame in range(frames)] for index, name in enumerate(names)]
    delay = start_at - time.time()
    if delay > 0:
        time.sleep(delay)
    start = time.time()
    if not paced:
        for frame in range(frames):
            for transport, topic, stream in zip(transports, topics, streams, strict=True):
                transport.publish(topic, stream[frame])
    else:
        for frame in range(frames):
            delay = start + frame / fps - time.time()
            if delay > 0:
                time.sleep(delay)
            for index, (transport, topic) in enumerate(zip(transports, topics, strict=True)):
                transport.publish(topic, _payload(names[index], index, frame,
                                                  start + frame / fps, people))
    flushed = all(transport.flush(300) for transport in transports)
    for transport in transports:
        transport.close()
    results.put({"start": start, "flushed": flushed})


# --------------------------------------------------------------------------- subscriber


class _FirstRow(msgspec.Struct):
    timestamp: float


class _Update(msgspec.Struct):
    tracks: list[_FirstRow]


def _subscribe(kind: str, address: str, ready: Any, stop: Any, results: Any) -> None:
    """Child process: latency of every track update, from its capture time to its arrival."""
    decoder = msgspec.json.Decoder(_Update)
    latencies: list[float] = []

    def arrived(payload: bytes | bytearray) -> None:
        now = time.time()
        update = decoder.decode(payload)
        if update.tracks:
            latencies.append(now - update.tracks[0].timestamp)

    if kind == "mosquitto":

        client = mqtt.Client(callback_api_version=CallbackAPIVersion.VERSION2,
                             client_id="bench-viewer", protocol=mqtt.MQTTv5)
        client.on_message = lambda client, userdata, message: arrived(message.payload)
        client.on_subscribe = lambda *args: ready.set()
        host, port = address.rsplit(":", 1)
        client.connect(host, int(port))
        client.subscribe(f"cblrs/{PLANE_ID}/tracks", qos=0)
        client.loop_start()
        stop.wait()
        client.loop_stop()
    else:
        # optional extra: pip install cblrs[nats]
        import nats

        async def main() -> None:
            connection = await nats.connect(servers=address.split(","), name="bench-viewer")

            async def deliver(msg: Any) -> None:
                arrived(msg.data)

            await connection.subscribe(f"cblrs.{PLANE_ID}.tracks", cb=deliver)
            await connection.flush()
            ready.set()
            while not stop.is_set():
                await asyncio.sleep(0.05)
            await connection.close()

        asyncio.run(main())
    results.put(latencies)


# --------------------------------------------------------------------------- one run


class _Probe:
    def __init__(self) -> None:
        self.stored = 0
        self.last_stored = 0.0
        self.last_group = 0.0

    def on_stored(self, entries: Any, wall_time: float) -> None:
        self.stored += len(entries)
        self.last_stored = wall_time

    def on_group(self, timestamp: float, entries: Any, tracks: Any, wall_time: float) -> None:
        self.last_group = wall_time


def run_once(backbone: str, cameras: int, frames: int, fps: float, paced: bool,
             people: int, publish_window: int = 256) -> dict[str, Any]:
    """One run on fresh servers; returns rates, latencies and losses."""

    total = cameras * frames
    names = _camera_names(cameras)
    context = multiprocessing.get_context("spawn")
    with tempfile.TemporaryDirectory(prefix="cblrs-bench-backbone-") as folder:
        servers: Any
        if backbone == "mosquitto":
            port = free_port()
            # run_as root: the broker reads a private temporary folder (a benchmark only).
            files = write_broker_config(Path(folder) / "broker", [], [], port=port,
                                        run_as="root" if os.geteuid() == 0 else None,
                                        allow_anonymous=True, viewer=False, persistence=True)
            servers = MosquittoProcess.from_files(files).start()
            transport: Any = MqttTransport("bench-matcher", MqttSettings(port=port))
            publish_port, version, address = port, "mqttv5", f"127.0.0.1:{port}"
        else:
            nodes = 3 if backbone.startswith("nats-r3") else 1
            servers = NatsCluster.create(Path(folder) / "nats", nodes, mqtt=True).start()
            settings = NatsSettings.from_url(servers.url, publish_window=64)
            transport = NatsTransport("bench-matcher", settings, durable="cblrs-plane-1",
                                      lease=LeaseSettings("plane-1", 10.0, 30.0))
            for _ in range(100):  # a new cluster takes a moment to elect its leaders
                try:
                    transport.open()
                    break
                except Exception:
                    time.sleep(0.2)
            publish_port, version = servers.mqtt_ports[0], "mqttv311"
            address = ",".join(servers.urls)
        store = RuntimeStore(Path(folder) / "matcher.db")
        probe = _Probe()
        ready, stop, latencies = context.Event(), context.Event(), context.Queue()
        viewer = context.Process(target=_subscribe, args=(
            "mosquitto" if backbone == "mosquitto" else "nats", address, ready, stop, latencies))
        viewer.start()
        service = None
        try:
            service = MatcherService(
                transport, store, make_matcher("fusion", PlaneSet([PlaneSpec(
                    PLANE_ID, (0.0, 0.0), 40.0, 40.0)]), names), PLANE_ID, names,
                policy=ValidationPolicy(max_future_s=3600.0), window_s=2.0, observer=probe,
            )
            gc.freeze()
            service.start()
            ready.wait(30)
            results = context.Queue()
            if backbone.endswith("-native"):
                groups = [names[index::PUBLISHER_PROCESSES]
                          for index in range(min(PUBLISHER_PROCESSES, cameras))]
                start_at = time.time() + 3.0 + 0.05 * cameras  # every transport connected
                publishers = [context.Process(target=_publish_nats, args=(
                    servers.url, group, frames, fps, paced, people, publish_window, start_at,
                    results)) for group in groups]
            else:
                publishers = [context.Process(target=_publish, args=(
                    publish_port, version, cameras, frames, fps, paced, people, results))]
            for publisher in publishers:
                publisher.start()
            reports = [results.get(timeout=900) for _ in publishers]
            report = {"start": min(item["start"] for item in reports),
                      "flushed": all(item["flushed"] for item in reports)}
            for publisher in publishers:
                publisher.join(60)
            deadline = time.time() + 120
            while (probe.stored < total or not service.drained()) and time.time() < deadline:
                time.sleep(0.005)
            service.close(flush=True)
            time.sleep(0.3)  # the last track updates reach the subscriber
            stop.set()
            samples = latencies.get(timeout=30)
            viewer.join(10)
        finally:
            if viewer.is_alive():
                viewer.kill()
            if service is None:
                transport.close()
            store.close()
            servers.stop()
    row: dict[str, Any] = {
        "backbone": backbone, "cameras": cameras, "rate": "paced" if paced else "max",
        "messages": total, "stored": probe.stored, "flushed": report["flushed"],
        "stored_per_s": probe.stored / max(probe.last_stored - report["start"], 1e-9),
        "tracked_per_s": total / max(probe.last_group - report["start"], 1e-9),
        "track_p50_ms": math.nan, "track_p99_ms": math.nan, "updates": len(samples),
    }
    if paced and samples:
        row["track_p50_ms"] = 1000 * float(np.percentile(samples, 50))
        row["track_p99_ms"] = 1000 * float(np.percentile(samples, 99))
    return row


def benchmark_backbone(
    backbones: tuple[str, ...] = BACKBONES,
    cameras: tuple[int, ...] = (1, 10, 50),
    repeats: int = 3,
    max_messages: int = 20_000,
    paced_seconds: float = 5.0,
    fps: float = 30.0,
    people: int = 2,
    progress: Any = None,
    publish_window: int = 256,
) -> dict[str, Any]:
    """Every backbone x camera count x rate, ``repeats`` times; medians per row
    (``publish_window``: NATS-native cameras' publishes awaiting acknowledgement)."""
    info = machine_info()

    server = find_nats_server()
    info["nats_server"] = subprocess.run([server, "--version"], capture_output=True,
                                         text=True).stdout.strip() if server else None
    rows = []
    for count in cameras:
        for backbone in backbones:
            for paced in (False, True):
                frames = int(paced_seconds * fps) if paced else max(1, max_messages // count)
                runs = [run_once(backbone, count, frames, fps, paced, people, publish_window)
                        for _ in range(repeats)]
                row = dict(runs[0])
                for key, value in runs[0].items():
                    if isinstance(value, float):
                        row[key] = statistics.median(run[key] for run in runs)
                row["stored"] = min(run["stored"] for run in runs)
                row["runs"] = runs
                rows.append(row)
                if progress is not None:
                    progress(row)
    info["load_average_end"] = round(__import__("os").getloadavg()[0], 2)
    return {"machine": info, "repeats": repeats, "fps": fps, "people": people, "rows": rows,
            "publish_window": publish_window}


def backbone_report(result: dict[str, Any]) -> str:
    """The markdown table with the machine above it."""

    def cell(value: float, digits: int = 0) -> str:
        return "–" if math.isnan(value) else f"{value:.{digits}f}"

    info = result["machine"]
    lines = [
        f"Matcher service (fusion) with SQLite store, {result['people']} detections per message, "
        f"{result['fps']:g} fps when paced; publishers: one mosquitto_pub per camera (MQTT 5 to "
        f"Mosquitto, MQTT 3.1.1 to NATS's MQTT listener), or for *-native cblrs's NATS "
        f"transport per camera ({result.get('publish_window', 256)} publishes in flight each); "
        f"latency at a separate subscriber of "
        f"the tracks. {describe_machine(info)}; {info.get('nats_server')}; load "
        f"{info['load_average_1min']} at start, {info['load_average_end']} at end; medians of "
        f"{result['repeats']} runs.",
        "",
        "| backbone | cameras | rate | received+stored+acked msg/s | tracked msg/s "
        "| capture -> track at subscriber p50 / p99 ms | lost |",
        "|---|---:|---|---:|---:|---:|---:|",
    ]
    for row in result["rows"]:
        latency = ("–" if math.isnan(row["track_p50_ms"]) else
                   f"{cell(row['track_p50_ms'], 1)} / {cell(row['track_p99_ms'], 1)}")
        stored = "–" if row["rate"] == "paced" else cell(row["stored_per_s"])
        tracked = "–" if row["rate"] == "paced" else cell(row["tracked_per_s"])
        lines.append(f"| {row['backbone']} | {row['cameras']} | {row['rate']} | {stored} "
                     f"| {tracked} | {latency} | {row['messages'] - row['stored']} |")
    return "\n".join(lines)
