"""The load of ``cblrs bench mqtt``: simulated cameras' messages and the publisher processes.

A publisher child process simulates many cameras, through ``mosquitto_pub -l -q 1`` processes
(C) or one Python paho client per camera; :func:`measure_stages` times each matcher step
in-process, without a broker.
"""

from __future__ import annotations

import math
import os
import statistics
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.matcher.ordering import Orderer
from cblrs.runtime.matcher.retrack import state_text
from cblrs.runtime.matcher.store import InboxEntry, RuntimeStore
from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.transport.topics import detections_topic
from cblrs.runtime.wire import ValidationPolicy, encode_message

PLANE_ID = 1


PLANE = PlaneSpec(PLANE_ID, (0.0, 0.0), 40.0, 40.0)


def camera_names(count: int) -> list[str]:
    """``count`` camera ids: cam000, cam001, ..."""
    return [f"cam{index:03d}" for index in range(count)]


def frame_message(camera: str, index: int, frame: int, timestamp: float, people: int) -> bytes:
    """A message with ``people`` detections whose colours walk across the plane."""
    rng = np.random.default_rng(index * 100003 + frame)
    # People walk 0.6 m/s at 30 fps and start over every 750 frames, so that long runs stay
    # on the 40 m plane (a point off it has no location and costs the tracker nothing); more
    # than ten people stand in rows of ten.
    walked = 0.02 * (frame % 750)
    base = np.array(
        [[4.0 + 2 * (person % 10) + walked, 5.0 + 2 * (person % 10) + 3 * (person // 10)]
         for person in range(people)]
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


class CameraClocks:
    """When each simulated camera captures and stamps its frames.

    Real cameras do not capture at the same instants: each runs its own clock and its own
    frame timer, so frame ``f`` of camera ``k`` is stamped ``f / fps + offset_k + jitter``.
    ``spread_s`` spreads the per-camera offsets evenly over ``[0, spread_s]`` (in a random
    order of the cameras), ``jitter_s`` is the standard deviation of a per-frame jitter
    (clipped at a fifth of the frame period, so that frames stay in order). Both 0: every
    camera stamps frame ``f`` with the same time, as an idealised benchmark would.

    Args:
        spread_s: spread of the cameras' offsets, seconds.
        jitter_s: per-frame jitter, seconds.
        seed: of the cameras' order and the jitter.
    """

    def __init__(self, spread_s: float = 0.0, jitter_s: float = 0.0, seed: int = 0):
        if not (spread_s >= 0 and jitter_s >= 0):
            raise ValueError("clock spread and jitter must be >= 0")
        self.spread_s = float(spread_s)
        self.jitter_s = float(jitter_s)
        self.seed = int(seed)

    def times(self, cameras: int, frames: int, fps: float, start: float) -> np.ndarray:
        """(frames, cameras) capture times, seconds."""
        generator = np.random.default_rng(self.seed)
        offsets = np.zeros(cameras)
        if cameras > 1:
            offsets = generator.permutation(np.linspace(0.0, self.spread_s, cameras))
        limit = 0.2 / fps
        jitter = np.clip(generator.normal(0.0, self.jitter_s, (frames, cameras)), -limit, limit)
        if self.jitter_s == 0:
            jitter[:] = 0.0
        return start + np.arange(frames)[:, None] / fps + offsets[None, :] + jitter


def publisher(kind: str, port: int, cameras: int, frames: int, fps: float, paced: bool,
              people: int, results, clocks: CameraClocks | None = None) -> None:
    """Child process: simulate ``cameras`` cameras; put timing facts on ``results``."""
    clocks = clocks or CameraClocks()
    try:
        if kind == "mosquitto_pub":
            report = _publish_with_mosquitto_pub(port, cameras, frames, fps, paced, people,
                                                 clocks)
        else:
            report = _publish_with_paho(port, cameras, frames, fps, paced, people, clocks)
    except BaseException as error:
        results.put({"error": repr(error)})
        raise
    results.put(report)


def _frames(names: list[str], frames: int, fps: float, epoch: float, people: int,
            clocks: CameraClocks | None = None):
    times = (clocks or CameraClocks()).times(len(names), frames, fps, epoch)
    return [[frame_message(name, index, frame, float(times[frame, index]), people)
             for index, name in enumerate(names)] for frame in range(frames)]


def _paced(names: list[str], frames: int, fps: float, start: float, people: int,
           clocks: CameraClocks, send) -> None:
    """Send every camera's frames at their capture times: ``send(camera_index, payload)``.

    Each frame is encoded ahead of its capture time, as each real camera would do on its own
    device; the loop then only waits and sends.
    """
    times = clocks.times(len(names), frames, fps, start)
    order = np.argsort(times, axis=None, kind="stable")
    upcoming: dict[tuple[int, int], bytes] = {}

    def encode(frame: int) -> None:
        if frame < frames:
            for index, name in enumerate(names):
                upcoming[frame, index] = frame_message(name, index, frame,
                                                       float(times[frame, index]), people)

    encode(0)
    encoded = 0
    for flat in order.tolist():
        frame, index = divmod(flat, len(names))
        if frame >= encoded:
            encoded = frame + 1
            encode(encoded)
        delay = times[frame, index] - time.time()
        if delay > 0:
            time.sleep(delay)
        send(index, upcoming.pop((frame, index)))


def _publish_with_mosquitto_pub(port: int, cameras: int, frames: int, fps: float, paced: bool,
                                people: int, clocks: CameraClocks) -> dict:
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
                   for column in zip(*_frames(names, frames, fps, epoch, people, clocks),
                                     strict=True)]
    time.sleep(1.0 + 0.02 * cameras)  # every mosquitto_pub connected
    start = time.time()
    if paced:
        start += 0.2

        def send(index: int, payload: bytes) -> None:
            stdin = processes[index].stdin
            assert stdin is not None
            stdin.write(payload + b"\n")

        _paced(names, frames, fps, start, people, clocks, send)
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
                       people: int, clocks: CameraClocks) -> dict:
    settings = MqttSettings(port=port, max_inflight=1000)
    names = camera_names(cameras)
    transports = [MqttTransport(f"bench-{name}", settings, persistent=False) for name in names]
    for transport in transports:
        transport.connect()
    topics = [detections_topic(PLANE_ID, name) for name in names]
    start = time.time() + (0.2 if paced else 0.0)
    if paced:
        _paced(names, frames, fps, start, people, clocks,
               lambda index, payload: transports[index].publish(topics[index], payload))
    else:
        payloads = _frames(names, frames, fps, time.time() - frames / fps, people, clocks)
        start = time.time()
        for batch in payloads:
            for transport, topic, payload in zip(transports, topics, batch, strict=True):
                transport.publish(topic, payload)
    published = time.time()
    flushed = all(transport.flush(120) for transport in transports)
    for transport in transports:
        transport.close(timeout=5)
    return {"start": start, "published": published, "flushed": flushed}


def _best_seconds(function, number: int, repeats: int = 5) -> float:
    """Best mean time of ``function`` over ``repeats`` rounds of ``number`` calls, seconds."""
    best = math.inf
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(number):
            function()
        best = min(best, (time.perf_counter() - started) / number)
    return best


def _pipe_seconds(batch: list, rounds: int = 20) -> tuple[float, int]:
    """Best seconds to send ``batch`` through a ``multiprocessing`` pipe and receive it
    (both ends in this process), and its pickled size in bytes."""
    import multiprocessing
    import pickle

    reader, writer = multiprocessing.Pipe(duplex=False)
    best = math.inf
    for _ in range(rounds):
        received = threading.Thread(target=reader.recv)
        started = time.perf_counter()
        received.start()
        writer.send(batch)
        received.join()
        best = min(best, time.perf_counter() - started)
    reader.close()
    writer.close()
    return best, len(pickle.dumps(batch))


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
    # Tracker process: a group's messages rebuilt from its entries; a batch of released
    # groups through the pipe from the service (pickled, sent, received and unpickled).
    build = _best_seconds(lambda: [entry.message() for entry in groups[0]], 200) / cameras
    batch = [(epoch + frame / 30.0, group) for frame, group in enumerate(groups[:50])]
    pipe, pipe_bytes = _pipe_seconds(batch)
    pipe /= sum(len(group) for _, group in batch)
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
        for frame, group in enumerate(groups):  # as the tracker process: keys, no state
            keys = [(m.camera_id, m.sequence) for m in group]
            store.commit_group(keys, outputs[frame], None, epoch + frame / 30.0,
                               {"groups": 1}, replay=[(epoch + frame / 30.0, keys)])
        commit = (time.perf_counter() - started) / frames
        # Saving the matcher state (every few seconds of capture time, off the track path).
        state_save = _best_seconds(
            lambda: store.save_matcher_state(state_text(matcher.get_state())), 3, repeats=3)
        stored_bytes = store.used_bytes() / len(rows)  # inbox + track rows, per message
        store.close()
    alone, process = tracker_process_cpu(cameras, people, matcher_name,
                                         max(frames, -(-PROCESS_MESSAGES // cameras)))
    return {
        "cameras": cameras, "people": people, "matcher": matcher_name,
        "tracker_alone_us_per_message": 1e6 * alone,
        "tracker_process_us_per_message": 1e6 * process,
        "decode_us_per_message": 1e6 * decode,
        "insert_us_per_message": 1e6 * insert,
        "update_ms_per_group": 1e3 * statistics.median(steady),
        "update_us_per_message": 1e6 * statistics.median(steady) / cameras,
        "update_worst_ms": 1e3 * max(updates),
        "commit_ms_per_group": 1e3 * commit,
        "state_save_ms": 1e3 * state_save,
        "build_us_per_message": 1e6 * build,
        "pipe_us_per_message": 1e6 * pipe,
        "pipe_bytes_per_message": pipe_bytes / sum(len(group) for _, group in batch),
        "database_bytes_per_message": stored_bytes,
    }


def stages_line(row: dict, matcher: str) -> str:
    """One camera count's line of ``cblrs bench mqtt --stages`` (a :func:`measure_stages` row)."""
    return (
        f"{row['cameras']:3d} cameras: decode {row['decode_us_per_message']:5.1f} us/msg"
        f", inbox insert {row['insert_us_per_message']:5.1f} us/msg, {matcher} "
        f"update {row['update_ms_per_group']:5.2f} ms/group "
        f"({row['update_us_per_message']:5.0f} us/msg, worst frame "
        f"{row['update_worst_ms']:5.1f} ms), commit "
        f"{row['commit_ms_per_group']:5.2f} ms/group, matcher state save "
        f"{row['state_save_ms']:5.1f} ms; messages from entries "
        f"{row['build_us_per_message']:4.1f} us/msg, pipe {row['pipe_us_per_message']:4.1f}"
        f" us/msg ({row['pipe_bytes_per_message']:.0f} bytes); database "
        f"{row['database_bytes_per_message']:.0f} bytes/message; tracker process "
        f"{row['tracker_process_us_per_message']:.0f} us CPU/msg, the tracker alone "
        f"{row['tracker_alone_us_per_message']:.0f} us/msg "
        f"({100 * row['tracker_alone_us_per_message'] / row['tracker_process_us_per_message']:.0f}"
        " %)"
    )


PROCESS_MESSAGES = 2000
"""Messages :func:`tracker_process_cpu` tracks at least (CPU time is read in clock ticks)."""


def tracker_process_cpu(cameras: int, people: int, matcher_name: str,
                        frames: int) -> tuple[float, float]:
    """CPU seconds per message of the tracker alone and of the matcher service's tracker
    process on the same windows (ordered as the service orders them).

    The tracker process is the service's own (:class:`TrackerProcess`, a fork-server child
    writing to a SQLite store, track updates encoded), fed batches of up to 50 windows
    through its pipe as fast as it takes them, with no broker: its CPU beyond the tracker
    alone's is what the process adds (rebuilding messages is in both).
    """
    from cblrs.runtime.matcher.matcher_service import _process_context
    from cblrs.runtime.matcher.store import PENDING
    from cblrs.runtime.matcher.tracker_process import TrackerProcess

    names = camera_names(cameras)
    policy = ValidationPolicy(known_cameras=frozenset(names), max_future_s=3600.0)
    epoch = time.time() - frames / 30.0
    orderer = Orderer(names)
    entries = []
    for group in _frames(names, frames, 30.0, epoch, people, CameraClocks(0.01, 0.002)):
        for payload in group:
            entries.append(InboxEntry.from_wire(policy.decode_wire(payload, now=epoch)))
            orderer.add(entries[-1], 0.0)
    windows = orderer.release(0.0, force=True)
    matcher = make_matcher(matcher_name, PlaneSet([PLANE]), names)
    started = time.process_time()
    for timestamp, group in windows:
        matcher.update(timestamp, [entry.message() for entry in group])
    alone = time.process_time() - started
    with tempfile.TemporaryDirectory(prefix="cblrs-bench-") as folder:
        store = RuntimeStore(Path(folder) / "process.db")
        store.insert_messages([(entry, PENDING, epoch) for entry in entries])
        process = TrackerProcess(_process_context(),
                                 make_matcher(matcher_name, PlaneSet([PLANE]), names),
                                 store.share(), store.claim(), PLANE_ID, names, True)
        try:
            answers: list[str] = []
            # The process's CPU read after each answer: it may have exited by the time
            # "stopped" is read (its last sample then is that of its last batch's answer).
            samples: list[float] = []

            def collect() -> None:
                while not answers or answers[-1] not in ("stopped", "failed"):
                    answers.append(process.receive()[0])
                    try:
                        samples.append(process_cpu_seconds(process.process.pid))
                    except OSError:
                        pass

            collector = threading.Thread(target=collect)
            collector.start()
            time.sleep(0.5)  # started and resumed from the (empty) store
            before = process_cpu_seconds(process.process.pid)
            for start in range(0, len(windows), 50):
                process.submit(windows[start:start + 50])
            process.finish()
            collector.join()
            spent = (samples[-1] if samples else math.nan) - before
        finally:
            process.close(30)
            store.close()
    if answers[-1] != "stopped":
        raise RuntimeError("the tracker process failed")
    return alone / len(entries), spent / len(entries)


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def tracker_alone(cameras: int, people: int, matcher_name: str, frames: int,
                  clocks: CameraClocks | None = None) -> tuple[float, float]:
    """The tracker's own rate on the benchmark's messages: the same frames, decoded into
    inbox entries, ordered into windows as the service orders them, then timed through what
    the tracker process does with each window (build the messages from the entries,
    ``matcher.update``), in this process, with no broker, store or pipe.

    Returns:
        ``(messages per second of CPU, messages per second of wall time)``. CPU time is
        what the tracker does with a core of its own; wall time is what it does in one
        process on this machine as loaded as it is during the run (on a machine shared with
        other jobs a process gets a fraction of a core). The service's tracked messages/s
        (wall clock) over each is the share of the tracker's own rate it keeps (issue 20
        item 7).
    """
    names = camera_names(cameras)
    policy = ValidationPolicy(known_cameras=frozenset(names), max_future_s=3600.0)
    epoch = time.time() - frames / 30.0
    orderer = Orderer(names)
    for group in _frames(names, frames, 30.0, epoch, people, clocks):
        for payload in group:
            orderer.add(InboxEntry.from_wire(policy.decode_wire(payload, now=epoch)), 0.0)
    windows = orderer.release(0.0, force=True)
    matcher = make_matcher(matcher_name, PlaneSet([PLANE]), names)
    started, wall = time.process_time(), time.perf_counter()
    for timestamp, entries in windows:
        matcher.update(timestamp, [entry.message() for entry in entries])
    cpu, wall = time.process_time() - started, time.perf_counter() - wall
    return cameras * frames / max(cpu, 1e-9), cameras * frames / max(wall, 1e-9)
