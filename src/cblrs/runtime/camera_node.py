"""The edge camera node: capture -> label -> locate -> transmit (the paper's Fig. 4, left).

For each frame of a :mod:`~cblrs.runtime.sources` source the node targets a pixel in every
box, reads the reference colour there (:func:`cblrs.edge.make_message`) and publishes the
message (QoS 1) on ``cblrs/<plane>/<camera>/detections``. Only boxes and colours leave the
camera. While the broker is away, the transport queues publishes and sends them on
reconnection; the node keeps going.

Capture timestamps. A recorded source gives times relative to its start (``scene_timestamp``);
the node maps them to wall time as ``epoch + scene_timestamp`` (``epoch + scene_timestamp /
speed`` with ``--realtime --speed``) so that a matcher's staleness checks (``max_age_s`` /
``max_future_s``) make sense; with ``--realtime`` each frame is published at that time.
Every camera of one replay must use the same ``epoch`` (``--epoch``), or timestamps of the
same frame would differ between cameras and never be grouped. Without one, the node picks
``now - first_timestamp`` when pacing in real time (the first frame is "now") and
``now - last_timestamp`` when replaying as fast as possible (the whole recording lies in the
recent past, never in the future). Live sources (``timestamp=None``) are stamped with the
wall clock at capture.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cblrs.edge import make_message
from cblrs.reference import ReferenceImage
from cblrs.runtime.sources import SourceFrame
from cblrs.runtime.topics import detections_topic, status_topic, validate_camera_id
from cblrs.runtime.wire import encode_message, encode_status
from cblrs.targeting import TargetingPosition

logger = logging.getLogger(__name__)


def camera_last_will(plane_id: int, camera_id: str) -> tuple[str, bytes]:
    """``(topic, payload)`` of a camera's last will: retained "offline" on its status topic."""
    return status_topic(plane_id, camera_id), encode_status(camera_id, "offline", role="camera")


@dataclass
class CameraReport:
    """What a camera node did.

    Attributes:
        camera_id: the camera.
        plane_id: the plane it published for.
        frames: frames read from the source.
        messages: messages published (one per frame).
        detections: boxes published.
        located: boxes whose target pixel saw a plane (colour B != 0).
        bytes: payload bytes published.
        first_sequence: sequence number of the first message.
        next_sequence: sequence number the next message would have had.
        elapsed_s: wall time from the first to the last publish, seconds.
        flushed: whether every message was acknowledged by the broker at the end.
        epoch: the epoch added to recorded timestamps, seconds since the Unix epoch.
    """

    camera_id: str
    plane_id: int
    frames: int = 0
    messages: int = 0
    detections: int = 0
    located: int = 0
    bytes: int = 0
    first_sequence: int = 0
    next_sequence: int = 0
    elapsed_s: float = 0.0
    flushed: bool = False
    epoch: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        data = {key: value for key, value in self.__dict__.items() if key != "extra"}
        data.update(self.extra)
        data["messages_per_s"] = self.messages / self.elapsed_s if self.elapsed_s > 0 else None
        return data


class CameraNode:
    """One edge camera publishing its detections.

    Args:
        transport: a connected-or-connectable :class:`~cblrs.runtime.transport.Transport`
            (give MQTT transports :func:`camera_last_will` as their will).
        plane_id: the plane (B channel) whose matcher receives the messages.
        camera_id: this camera's id (a topic level).
        reference: the camera's reference image.
        realtime: pace publishing by the recorded timestamps; else as fast as possible.
        speed: with ``realtime``, play this many times faster than recorded (recorded
            times are divided by ``speed`` before the epoch is added).
        epoch: seconds added to recorded timestamps (see the module docstring).
        first_sequence: sequence number of the first message; replays restart at the same
            number, so a matcher ignores frames it already has.
        targeting: per-class targeting overrides.
        drop_hidden_feet: no location for boxes whose feet a nearer box hides (for a
            detector's boxes; see :func:`cblrs.edge.feet_hidden`).
        flush_timeout_s: how long to wait at the end for the broker to acknowledge
            everything (queued messages included).
        clock: wall clock, seconds since the Unix epoch.
    """

    def __init__(
        self,
        transport: Any,
        plane_id: int,
        camera_id: str,
        reference: ReferenceImage,
        *,
        realtime: bool = False,
        speed: float = 1.0,
        epoch: float | None = None,
        first_sequence: int = 0,
        targeting: dict[str, TargetingPosition] | None = None,
        drop_hidden_feet: bool = False,
        flush_timeout_s: float = 30.0,
        clock: Callable[[], float] = time.time,
    ):
        validate_camera_id(camera_id)
        if speed <= 0:
            raise ValueError(f"speed must be positive, got {speed}.")
        self.transport = transport
        self.plane_id = int(plane_id)
        self.camera_id = camera_id
        self.reference = reference
        self.realtime = realtime
        self.speed = float(speed)
        self.epoch = epoch
        self.first_sequence = int(first_sequence)
        self.targeting = targeting
        self.drop_hidden_feet = bool(drop_hidden_feet)
        self.flush_timeout_s = float(flush_timeout_s)
        self._clock = clock
        self._stop = threading.Event()
        self.topic = detections_topic(self.plane_id, camera_id)
        self.status_topic = status_topic(self.plane_id, camera_id)

    def stop(self) -> None:
        """Ask :meth:`run` to finish after the current frame (thread-safe)."""
        self._stop.set()

    def run(self, frames: Iterable[SourceFrame], connect: bool = True) -> CameraReport:
        """Publish every frame of ``frames``; returns the counts.

        The status topic says "online" (retained) at the start and "offline" at a clean end;
        a crash leaves the transport's last will.
        """
        report = CameraReport(self.camera_id, self.plane_id, first_sequence=self.first_sequence)
        if connect:
            self.transport.connect()
        self.transport.publish(
            self.status_topic,
            encode_status(self.camera_id, "online", role="camera", timestamp=self._clock()),
            qos=1,
            retain=True,
        )
        sequence = self.first_sequence
        started: float | None = None
        try:
            for item in self._timed(frames, report):
                if self._stop.is_set():
                    break
                frame, capture_time = item
                message = make_message(
                    self.camera_id, sequence, capture_time, frame.frame, frame.detections,
                    self.reference, self.targeting, drop_hidden_feet=self.drop_hidden_feet,
                )
                payload = encode_message(message, self.plane_id)
                self.transport.publish(self.topic, payload, qos=1)
                if started is None:
                    started = time.perf_counter()
                report.elapsed_s = time.perf_counter() - started
                sequence += 1
                report.messages += 1
                report.detections += len(message)
                report.located += int(np.count_nonzero(message.colour[:, 2]))
                report.bytes += len(payload)
        finally:
            report.next_sequence = sequence
            self.transport.publish(
                self.status_topic,
                encode_status(self.camera_id, "offline", role="camera", timestamp=self._clock()),
                qos=1,
                retain=True,
            )
            report.flushed = bool(self.transport.flush(self.flush_timeout_s))
            if not report.flushed:
                logger.warning(
                    "camera %s: not every message was acknowledged within %.0f s",
                    self.camera_id, self.flush_timeout_s,
                )
        return report

    def _timed(
        self, frames: Iterable[SourceFrame], report: CameraReport
    ) -> Iterator[tuple[SourceFrame, float]]:
        """Frames with their capture times, sleeping between them when pacing."""
        iterator = iter(frames)
        pending: list[SourceFrame] = []
        epoch = self.epoch
        if epoch is None and not self.realtime:
            # As fast as possible: place the whole recording in the recent past, which needs
            # its last timestamp, so read the (finite) recorded source up front.
            pending = list(iterator)
            iterator = iter(())
            times = [frame.timestamp for frame in pending if frame.timestamp is not None]
            if times:
                epoch = self._clock() - max(times)
        scale = 1.0 / self.speed if self.realtime else 1.0
        for frame in _chain(pending, iterator):
            report.frames += 1
            if frame.timestamp is None:
                yield frame, self._clock()
                continue
            recorded = frame.timestamp * scale
            if epoch is None:
                epoch = self._clock() - recorded
            report.epoch = epoch
            capture_time = epoch + recorded
            if self.realtime:
                # Publish each frame at its capture time: cameras sharing an epoch follow
                # one wall-clock schedule.
                delay = capture_time - self._clock()
                if delay > 0 and self._stop.wait(delay):
                    return
            yield frame, capture_time


def _chain(first: list[SourceFrame], rest: Iterator[SourceFrame]) -> Iterator[SourceFrame]:
    yield from first
    yield from rest
