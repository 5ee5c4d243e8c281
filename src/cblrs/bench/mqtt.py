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
* ``transport``: :class:`~cblrs.runtime.transport.protocol.MqttTransport` with a handler that only
  acknowledges (the runtime's transport wrapper);
* ``matcher``: the full :class:`~cblrs.runtime.matcher.matcher_service.MatcherService`: validation,
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
  (a paho client on ``cblrs/<plane>/tracks``, one sample per update, i.e. per frame), over
  every frame and over the frames after each camera's first :data:`WARM_UP_FRAMES` (and the
  slowest update of the first :data:`FIRST_FRAMES` frames); each
  group's time after its last camera's message is split at its release from the ordering
  buffer (the service's ``on_released`` observer hook).

Camera clocks: by default each simulated camera stamps and publishes its frames with its own
clock, as real cameras do: offsets spread over 10 ms (``--clock-spread-ms``) and a per-frame
jitter of 2 ms (``--clock-jitter-ms``), so the frames of one instant arrive a few ms apart.
``--clock-spread-ms 0 --clock-jitter-ms 0`` stamps every camera's frame with the same time (an
idealised case, which benchmarks before issue 20 measured).

The matcher is told the cameras' frame rate (``camera_fps``, as ``cblrs matcher --camera-fps``
is), so it predicts a camera's next frame from its first one on; ``--unknown-fps`` does not
tell it (before issue 20's fix): until it has measured a camera's period from its first four
frames, each of those frames waits for the camera's next one.

``--nagle`` leaves Nagle's algorithm on (no ``TCP_NODELAY`` on the matcher's, the broker's and
the subscriber's sockets), as cblrs did before issue 10: small packets (a track update, an
acknowledgement) then wait for the previous one's TCP acknowledgement.

Matcher rows at ``max`` also time the tracker alone on the same messages (ordered as the
service orders them, messages built from inbox entries, ``matcher.update``; no broker, store
or pipe), in messages per second of CPU (what it does with a core of its own) and of wall
time (what it does in one process at the run's load), and print the service's tracked rate
as a share of each.

Printed figures are medians over ``--repeats`` runs, with the machine (CPU, cores, load
average at start and end). Not a test: nothing is asserted.

Usage::

    cblrs bench mqtt                 # 1, 10, 50 cameras, 3 repeats
    cblrs bench mqtt --cameras 50 --repeats 5 --json
    cblrs bench mqtt --stages        # per-step costs in-process, no broker
"""

from __future__ import annotations

import gc
import json
import math
import multiprocessing
import os
import socket
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

from cblrs.bench.mqtt_load import (
    PLANE,
    PLANE_ID,
    CameraClocks,
    camera_names,
    measure_stages,
    process_cpu_seconds,
    publisher,
    stages_line,
    tracker_alone,
)
from cblrs.bench.mqtt_report import (
    FIRST_FRAMES,
    WARM_UP_FRAMES,
    clocks_text,
    format_value,
    machine,
    markdown_table,
    median_of,
)
from cblrs.matching import make_matcher
from cblrs.plane import PlaneSet
from cblrs.runtime.broker.mosquitto_config import MosquittoProcess, free_port, write_broker_config
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.transport.topics import detections_filter, tracks_topic
from cblrs.runtime.wire import ValidationPolicy

RECEIVERS = ("broker", "paho", "transport", "matcher")

DEFAULT_RUNS = ("broker/max", "paho/max", "transport/max", "matcher/max", "paho/paced",
                "matcher/paced")


class _Timestamp(msgspec.Struct):
    timestamp: float


_timestamp_decoder = msgspec.json.Decoder(_Timestamp)


class Probe:
    """Observer of the matcher service: receipt and track-output times per message, and per
    group where the time went: from the group's mean capture time to the receipt of its last
    message (waiting for the last camera and receiving it), then to the track output, split
    into the wait in the ordering buffer (until the group is released to the tracker
    process) and what follows (the pipe, the tracker process, its commit, publishing)."""

    def __init__(self) -> None:
        self.receipt: list[float] = []
        self.tracked: list[float] = []
        self.last_member: list[float] = []
        self.after_last: list[float] = []
        self.to_release: list[float] = []
        self.after_release: list[float] = []
        self._stored_at: dict[tuple[str, int], float] = {}
        self._released_at: dict[float, float] = {}
        self.last_stored = 0.0
        self.last_group = 0.0
        self.stored = 0

    def on_stored(self, messages, wall_time) -> None:
        self.receipt.extend(wall_time - message.timestamp for message in messages)
        for message in messages:
            self._stored_at[message.camera_id, message.sequence] = wall_time
        self.last_stored = wall_time
        self.stored += len(messages)

    def on_released(self, timestamps, wall_time) -> None:
        for timestamp in timestamps:
            self._released_at[timestamp] = wall_time

    def on_group(self, timestamp, messages, tracks, wall_time) -> None:
        self.tracked.extend(wall_time - message.timestamp for message in messages)
        self.last_group = wall_time
        stored = [self._stored_at.pop((message.camera_id, message.sequence), math.nan)
                  for message in messages]
        released = self._released_at.pop(timestamp, math.nan)
        if messages and not any(math.isnan(value) for value in stored):
            capture = statistics.fmean(message.timestamp for message in messages)
            self.last_member.append(max(stored) - capture)
            self.after_last.append(wall_time - max(stored))
            if not math.isnan(released):
                self.to_release.append(released - max(stored))
                self.after_release.append(wall_time - released)


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
    """Child process: a paho client on the tracks topic; ``(capture time, capture -> arrival
    latency)`` of each track update (its rows carry the frame's capture time)."""

    latencies: list[tuple[float, float]] = []
    client = mqtt.Client(callback_api_version=CallbackAPIVersion.VERSION2,
                         client_id="bench-tracks", protocol=mqtt.MQTTv5)
    if not nagle:
        client.on_socket_open = lambda c, u, sock: sock.setsockopt(  # type: ignore[attr-defined]
            socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def on_message(client, userdata, message) -> None:
        now = time.time()
        update = _update_decoder.decode(message.payload)
        if update.tracks:
            latencies.append((update.tracks[0].timestamp, now - update.tracks[0].timestamp))

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
             paced: bool, people: int, matcher_name: str, nagle: bool = False,
             clocks: CameraClocks | None = None, known_fps: bool = True) -> dict:
    """One run: a Mosquitto on a free port, the receiver in this process, the publishers in
    others; the run's counts, rates and latency percentiles (milliseconds). ``clocks``: when
    the cameras capture and stamp their frames (default: all at the same instants);
    ``known_fps``: the matcher is told the cameras' frame rate."""
    clocks = clocks or CameraClocks()
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
        subscriber_latencies: list[tuple[float, float]] = []
        subscriber_results: multiprocessing.Queue = multiprocessing.Queue()
        subscriber_stop = multiprocessing.Event()
        receiver = _Receiver(total, paced)
        probe = Probe()
        cpu: dict[str, float] = {}
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
                    observer=probe, camera_fps=fps if known_fps else None,
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
                service_cpu = time.process_time()
            results: multiprocessing.Queue = multiprocessing.Queue()
            process = multiprocessing.Process(
                target=publisher,
                args=(publisher_kind, port, cameras, frames, fps, paced, people, results, clocks),
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
                # Where the CPU went: this process (receiver, ordering, publishing, and this
                # benchmark's own waiting) and the tracker process (from /proc, Linux).
                cpu["service"] = time.process_time() - service_cpu
                cpu["tracker"] = _process_cpu_seconds(service)
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
        "subscriber_p50_ms": math.nan, "subscriber_p99_ms": math.nan,
        "subscriber_steady_p50_ms": math.nan, "subscriber_steady_p99_ms": math.nan,
        "nagle": nagle, "known_fps": known_fps,
        "clock_spread_ms": 1000 * clocks.spread_s, "clock_jitter_ms": 1000 * clocks.jitter_s,
    }
    if paced and receiver.receipt:
        row["receipt_p50_ms"] = 1000 * float(np.percentile(receiver.receipt, 50))
        row["receipt_p99_ms"] = 1000 * float(np.percentile(receiver.receipt, 99))
    if service is not None:
        row["tracked_per_s"] = total / max(probe.last_group - report["start"], 1e-9)
        row["service_cpu_us_per_message"] = 1e6 * cpu.get("service", math.nan) / total
        row["tracker_cpu_us_per_message"] = 1e6 * cpu.get("tracker", math.nan) / total
        # The share of a core the tracker process had from the first publish to the last
        # group tracked: near 1, its own CPU bounds the tracked rate; far below, the cores
        # went to the service, the broker, the publishers and other jobs.
        row["tracker_core_share"] = cpu.get("tracker", math.nan) / max(
            probe.last_group - report["start"], 1e-9)
        row["late"], row["rejected"] = stats["late"], stats["rejected"]
        if paced:  # in max runs capture times are synthetic: latencies would mean nothing
            row["receipt_p50_ms"] = 1000 * float(np.percentile(probe.receipt, 50))
            row["receipt_p99_ms"] = 1000 * float(np.percentile(probe.receipt, 99))
            row["track_p50_ms"] = 1000 * float(np.percentile(probe.tracked, 50))
            row["track_p99_ms"] = 1000 * float(np.percentile(probe.tracked, 99))
            if probe.last_member:
                for name, values in (("last_member", probe.last_member),
                                     ("after_last", probe.after_last),
                                     ("to_release", probe.to_release),
                                     ("after_release", probe.after_release)):
                    if values:
                        row[f"{name}_p50_ms"] = 1000 * float(np.percentile(values, 50))
                        row[f"{name}_p99_ms"] = 1000 * float(np.percentile(values, 99))
            if subscriber_latencies:
                latencies = [latency for _, latency in subscriber_latencies]
                row["subscriber_p50_ms"] = 1000 * float(np.percentile(latencies, 50))
                row["subscriber_p99_ms"] = 1000 * float(np.percentile(latencies, 99))
                row["subscriber_updates"] = len(latencies)
                # After the warm-up: until the ordering knows each camera's frame period
                # (and is not told the cameras' frame rate), a frame's window waits for
                # the next frame. The first frames' own figure shows whether they wait.
                first = [latency for capture, latency in subscriber_latencies
                         if capture < report["start"] + FIRST_FRAMES / fps]
                if first:
                    row["subscriber_first_max_ms"] = 1000 * max(first)
                settled = report["start"] + WARM_UP_FRAMES / fps
                steady = [latency for capture, latency in subscriber_latencies
                          if capture >= settled]
                if steady:
                    row["subscriber_steady_p50_ms"] = 1000 * float(np.percentile(steady, 50))
                    row["subscriber_steady_p99_ms"] = 1000 * float(np.percentile(steady, 99))
                    row["subscriber_steady_updates"] = len(steady)
    return row


def _process_cpu_seconds(service: MatcherService) -> float:
    """User + system CPU seconds of the service's tracker process so far (NaN if unknown)."""
    tracker = getattr(service, "_tracker", None)
    pid = getattr(getattr(tracker, "process", None), "pid", None)
    try:
        return process_cpu_seconds(pid)
    except (OSError, IndexError, ValueError):
        return math.nan


def check_runs(runs: list[str]) -> str | None:
    """One sentence on what is wrong with these ``receiver/rate`` pairs, or None."""
    for run in runs:
        receiver, _, rate = run.partition("/")
        if receiver not in RECEIVERS or rate not in ("max", "paced"):
            return f"bad run {run!r}: expected <{'|'.join(RECEIVERS)}>/<max|paced>."
        if receiver == "broker" and rate == "paced":
            return "the broker receiver (mosquitto_sub) measures max throughput only."
    return None


def run_mqtt_benchmark(args: Any) -> int:
    """Run ``cblrs bench mqtt`` with its parsed options; print rows as they are measured.

    ``args`` carries the options of ``cblrs bench mqtt --help`` (cameras, runs, publisher,
    repeats, max_messages, paced_seconds, fps, people, matcher, nagle, stages, json, markdown,
    out: a folder for ``bench_mqtt.json`` and ``bench_mqtt.md``, or None).
    """
    out = getattr(args, "out", None)
    if args.stages:
        stage_rows = [measure_stages(cameras, args.people, args.matcher)
                      for cameras in args.cameras]
        stages_document = {"machine": machine(), "stages": stage_rows}
        lines = [stages_line(row, args.matcher) for row in stage_rows]
        print(json.dumps(stages_document, indent=2) if args.json else "\n".join(lines))
        if out is not None:
            _write_results(Path(out), "mqtt_stages", stages_document, "\n".join(lines))
        return 0
    problem = check_runs(args.runs)
    if problem is not None:
        raise ValueError(problem)
    info = machine()
    info["load_start"] = list(os.getloadavg())
    if not (args.json or args.markdown):
        print(f"{info['cpu']}, {info['cores']} cores, Python {info['python']}, "
              f"{info['mosquitto']}, paho-mqtt {info['paho-mqtt']}; publisher: "
              f"{args.publisher}; {clocks_text(args)}; load average "
              f"{info['load_start'][0]:.2f}", flush=True)
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
                             args.people, args.matcher, args.nagle,
                             CameraClocks(args.clock_spread_ms / 1000,
                                          args.clock_jitter_ms / 1000, seed=repeat),
                             known_fps=not getattr(args, "unknown_fps", False))
                    for repeat in range(args.repeats)]
            if receiver == "matcher" and not paced:
                # The tracker's own rate on the same messages, between the service's runs.
                for repeat, one in enumerate(runs):
                    one["tracker_alone_per_s"], one["tracker_alone_wall_per_s"] = \
                        tracker_alone(cameras, args.people, args.matcher, min(frames, 600),
                                      CameraClocks(args.clock_spread_ms / 1000,
                                                   args.clock_jitter_ms / 1000, seed=repeat))
            row = median_of(runs)
            row["runs"] = runs
            rows.append(row)
            if not (args.json or args.markdown):
                print(
                    f"{cameras:4d} {receiver:9s} {rate:5s} {row['messages']:6d} "
                    f"{row['received_per_s']:8.0f} {format_value(row['tracked_per_s'], 8, 0)} | "
                    f"{format_value(row['receipt_p50_ms'], 11)} "
                    f"{format_value(row['receipt_p99_ms'])} | "
                    f"{format_value(row['track_p50_ms'], 9)} {format_value(row['track_p99_ms'])} | "
                    f"{format_value(row['subscriber_p50_ms'], 10)} "
                    f"{format_value(row['subscriber_p99_ms'])} | "
                    f"{row['messages'] - row['received']:4d} {row['late']:4d}",
                    flush=True,
                )
                if receiver == "matcher":
                    print(f"{'':20s} CPU per message: service process "
                          f"{row['service_cpu_us_per_message']:.0f} us, tracker process "
                          f"{row['tracker_cpu_us_per_message']:.0f} us; the tracker process "
                          f"had {100 * row['tracker_core_share']:.0f} % of a core while the "
                          "service tracked", flush=True)
                if "tracker_alone_per_s" in row:
                    print(f"{'':20s} the tracker alone on these messages: "
                          f"{row['tracker_alone_per_s']:.0f} msg per CPU second, "
                          f"{row['tracker_alone_wall_per_s']:.0f} msg/s of wall time in this "
                          "process (the same load); the service tracked "
                          f"{100 * row['tracked_per_s'] / row['tracker_alone_per_s']:.0f} % "
                          f"and {100 * row['tracked_per_s'] / row['tracker_alone_wall_per_s']:.0f}"
                          " % of them", flush=True)
                if "last_member_p50_ms" in row:
                    print(f"{'':20s} capture -> last member received p50/p99 "
                          f"{row['last_member_p50_ms']:.1f}/{row['last_member_p99_ms']:.1f} ms,"
                          f" then -> track output {row['after_last_p50_ms']:.1f}/"
                          f"{row['after_last_p99_ms']:.1f} ms (in the ordering buffer "
                          f"{row.get('to_release_p50_ms', math.nan):.1f}/"
                          f"{row.get('to_release_p99_ms', math.nan):.1f} ms, then tracker "
                          f"process and publishing {row.get('after_release_p50_ms', math.nan):.1f}"
                          f"/{row.get('after_release_p99_ms', math.nan):.1f} ms)", flush=True)
                if "subscriber_first_max_ms" in row:
                    print(f"{'':20s} tracks at the subscriber of the first {FIRST_FRAMES} "
                          f"frames: at most {row['subscriber_first_max_ms']:.1f} ms",
                          flush=True)
                if not math.isnan(row["subscriber_steady_p50_ms"]):
                    print(f"{'':20s} tracks at the subscriber after each camera's first "
                          f"{WARM_UP_FRAMES} frames p50/p99 "
                          f"{row['subscriber_steady_p50_ms']:.1f}/"
                          f"{row['subscriber_steady_p99_ms']:.1f} ms", flush=True)
    info["load_end"] = list(os.getloadavg())
    document = {"machine": info, "publisher": args.publisher, "repeats": args.repeats,
                "fps": args.fps, "people": args.people, "matcher": args.matcher,
                "clock_spread_ms": args.clock_spread_ms,
                "clock_jitter_ms": args.clock_jitter_ms, "results": rows}
    if out is not None:
        _write_results(Path(out), "mqtt", document, markdown_table(info, rows, args))
    if args.markdown:
        print(markdown_table(info, rows, args))
    elif args.json:
        print(json.dumps(document, indent=2).replace("NaN", "null"))
    else:
        print(f"load average at end {info['load_end'][0]:.2f} (1 min), "
              f"{info['load_end'][1]:.2f} (5 min); medians over {args.repeats} runs")
    return 0


def _write_results(out: Path, name: str, document: dict[str, Any], text: str) -> None:
    """``bench_<name>.json`` and ``bench_<name>.md`` in ``out`` (as every benchmark writes)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"bench_{name}.json").write_text(
        json.dumps(document, indent=2).replace("NaN", "null") + "\n")
    (out / f"bench_{name}.md").write_text(text + "\n")
