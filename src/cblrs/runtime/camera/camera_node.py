"""The edge camera node: capture -> label -> locate -> transmit (the paper's Fig. 4, left).

For each frame of a :mod:`~cblrs.runtime.camera.sources` source the node targets a pixel in every
box, reads the reference colour there (:func:`cblrs.edge.make_message`) and publishes the
message (QoS 1) on ``cblrs/<plane>/<camera>/detections``. Only boxes and colours leave the
camera.

Delivery. Every message goes to the camera's spool (:mod:`cblrs.runtime.camera.spool`) first; a
*pump* thread hands spooled messages to the transport in sequence order, at most ``window``
at a time, and the spool forgets a message only when the plane's matcher confirms it stored
it (:mod:`cblrs.runtime.matcher.confirmations`). A message the broker acknowledged but the matcher
has not confirmed is sent again (the matcher recognises duplicates by camera and sequence):

* at once when a matcher announces itself "online" with a new session (the broker held
  nothing for it, e.g. it never subscribed before, or the broker lost its state; a retained
  announcement from before this camera connected does not count);
* when the matcher confirms a message but not earlier ones the broker had acknowledged
  before it (the matcher stores a camera's messages in order, so those were dropped between
  broker and matcher: a full queue, a crash between two saves of the broker's database);
* when confirmations stall: a matcher is online, and for ``resend_after_s`` nothing was
  confirmed while acknowledged messages wait (the same losses at the end of a stream); the
  wait doubles after each round, up to 5 minutes.

A broker's refusal (an MQTT 5 reason code >= 0x80, e.g. "Not authorized" from the ACL) stops
the node: it is a configuration mistake, reported in one sentence
(:attr:`CameraReport.refusal`); the refused messages stay in the spool.

Boxes the camera cannot stand behind are dropped and counted by reason
(:func:`cblrs.edge.box_rejections`: not finite, inverted, entirely outside the image), and a
frame whose message would exceed ``max_bytes`` is dropped and counted.

Capture timestamps. A recorded source gives times relative to its start (``scene_timestamp``);
the node maps them to wall time as ``epoch + scene_timestamp`` (``epoch + scene_timestamp /
speed`` with ``--realtime --speed``) so that a matcher's staleness checks (``max_age_s`` /
``max_future_s``) make sense; with ``--realtime`` each frame is published at that time.
Every camera of one replay must use the same ``epoch`` (``--epoch``), or timestamps of the
same frame would differ between cameras and never be grouped. Without one, the node picks
``now - first_timestamp`` when pacing in real time (the first frame is "now") and
``now - last_timestamp`` when replaying as fast as possible (the whole recording lies in the
recent past, never in the future). A sped-up replay therefore shows the matcher everyone
moving ``speed`` times faster: its tracks are a load test's, not the recording's (measured on
WILDTRACK's first 120 frames: 132 track ids at speed 1, 323 at 10 and 338 at 25, for twelve
times the tracker's CPU); replaying as fast as possible keeps the recorded spacing. Live
sources (``timestamp=None``) are stamped with the wall clock at capture.

Status. The node publishes a retained, timestamped "online" on its status topic at the start
and after every reconnection, and at the end a timestamped "offline" — the matcher's sign
that the stream has ended — only once everything it sent is accounted for (acknowledged by
the broker, or, when it waits for confirmations, confirmed by the matcher). Otherwise — and
when it is stopped (a signal) before its source ended — it ends with an untimestamped
"offline", like its last will: the connection ended, the stream did not, and the matcher
keeps waiting for the rest.

:class:`CameraNode` keeps the run: the capture loop, the spool pump and the pacing; its state is
in :mod:`~cblrs.runtime.camera.camera_state`, the delivery side (results, confirmations,
resends) in :mod:`~cblrs.runtime.camera.camera_delivery`, the run's counts
(:class:`~cblrs.runtime.camera.camera_report.CameraReport`) in
:mod:`~cblrs.runtime.camera.camera_report`; the spool, the sources and the transports are their
own modules.
"""

from __future__ import annotations

import functools
import inspect
import logging
import threading
import time
from collections.abc import Iterable, Iterator

import numpy as np

from cblrs.datasets.images import SkippedImages
from cblrs.detections import Detections
from cblrs.edge import box_rejections, make_message
from cblrs.runtime.camera.camera_delivery import _CameraDelivery
from cblrs.runtime.camera.camera_report import CameraReport
from cblrs.runtime.camera.sources import SourceFrame
from cblrs.runtime.camera.spool import Spool
from cblrs.runtime.transport.topics import (
    matcher_status_filter,
    status_topic,
    stored_topic,
)
from cblrs.runtime.wire import (
    encode_message,
    encode_status,
)

__all__ = ["STOP_FLUSH_S", "STOP_OFFLINE_S", "CameraNode", "CameraReport", "camera_last_will"]

logger = logging.getLogger(__name__)

_REMINDER_S = 60.0
# A first paced frame due later than _FIRST_WAIT_SAID_S is announced (INFO; a warning when
# later than _FIRST_WAIT_WARN_S): the replay is silent until then.
_FIRST_WAIT_SAID_S = 1.0
_FIRST_WAIT_WARN_S = 10.0
STOP_FLUSH_S = 5.0
"""A stopped node waits at most this long for the broker to take what it sent (the spool
keeps the rest), also when the stop comes during a longer wait at the end of its source."""
STOP_OFFLINE_S = 1.0
"""... and no longer than this while it has no connection to the broker."""


def camera_last_will(plane_id: int, camera_id: str) -> tuple[str, bytes]:
    """``(topic, payload)`` of a camera's last will: retained "offline" on its status topic."""
    return status_topic(plane_id, camera_id), encode_status(camera_id, "offline", role="camera")


class CameraNode(_CameraDelivery):
    """One edge camera publishing its detections.

    Args:
        transport: a connected-or-connectable :class:`~cblrs.runtime.transport.protocol.Transport`
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
            everything (spooled messages included).
        confirm_timeout_s: then, how long to wait for the matcher's confirmations (0: do not
            wait; a matcher that is online confirms within about a second).
        spool: where messages wait for confirmation (default: in memory, lost with the
            process; ``cblrs camera`` uses a file).
        resend_after_s: stall time after which unconfirmed messages are sent again.
        window: messages handed to the transport and not yet acknowledged, at most.
        max_bytes: largest message sent (the matcher's default limit); larger frames are
            dropped and counted.
        clear_retained: at the start, remove a retained message someone left on this
            camera's detections topic (an empty retained publish).
        clock: wall clock, seconds since the Unix epoch.
    """

    def stop(self) -> None:
        """Ask :meth:`run` to finish after the current frame (thread-safe); what is not
        acknowledged within a few seconds stays in the spool."""
        self._stop.set()
        self._wake.set()

    def fail(self, sentence: str) -> None:
        """The backbone refused this camera for good (e.g. its login, once the servers
        answered): stop, reported as :attr:`CameraReport.refusal` (thread-safe)."""
        with self._lock:
            first = self._refusal is None
            if first:
                self._refusal = sentence.rstrip(".")
        if first:
            logger.error("camera %s: %s; stopping", self.camera_id, self._refusal)
        self.stop()

    # -- the run ----------------------------------------------------------------------------

    def run(self, frames: Iterable[SourceFrame], connect: bool = True) -> CameraReport:
        """Publish every frame of ``frames``; returns the counts (see the module docstring)."""
        report = CameraReport(self.camera_id, self.plane_id, first_sequence=self.first_sequence)
        own_spool = self.spool is None
        spool = self.spool if self.spool is not None else Spool(None)
        self._spool = spool
        self.transport.subscribe(stored_topic(self.plane_id, self.camera_id), self._on_stored)
        self.transport.subscribe(matcher_status_filter(self.plane_id), self._on_matcher_status)
        add_hook = getattr(self.transport, "add_connect_hook", None)
        if add_hook is not None:
            add_hook(self._on_connected)
        # Without connect hooks (NATS) the pump says "online" once the transport connects.
        self._announce_when_connected = add_hook is None
        if connect:
            self.transport.connect()
        if not self._online_published and getattr(self.transport, "connected", True):
            self._announce("online")
        if self.clear_retained:
            self.transport.publish(self.topic, b"", qos=1, retain=True)
        # A transport without per-publish answers (NATS: its publishes are retried until the
        # stream takes them) counts a publish as acknowledged once handed over.
        parameters = inspect.signature(self.transport.publish).parameters
        self._answers = "on_result" in parameters
        # A transport that de-duplicates by message id (NATS) is told which publishes are
        # re-sends (see _pump).
        self._marks_resends = "resend" in parameters
        pump = threading.Thread(target=self._pump, name=f"cblrs-pump-{self.camera_id}",
                                daemon=True)
        pump.start()
        sequence = self.first_sequence
        started: float | None = None
        final = False
        failing = True  # until the source is read to its end (or the node was stopped)
        stopped = False  # stopped before the source ended: the stream goes on after a restart
        skipped = SkippedImages(f"camera {self.camera_id}")
        try:
            for frame, capture_time in self._timed(frames, report):
                if self._stop.is_set():
                    stopped = True
                    break
                if frame.unusable is not None:
                    # An unusable image: no message (a frame seen empty would be a claim).
                    skipped.skip(frame.unusable)
                    report.frames_skipped = dict(skipped.counts)
                    continue
                payload = self._encode(frame, sequence, capture_time, report)
                sequence += 1
                if payload is None:
                    continue
                if spool.append(sequence - 1, self.topic, payload):
                    with self._lock:
                        self._fresh.add(sequence - 1)
                else:
                    self._counts["already_spooled"] += 1
                self._wake.set()
                if started is None:
                    started = time.perf_counter()
                report.elapsed_s = time.perf_counter() - started
            # A stop during a paced wait ends the frames early too (_timed returns).
            stopped = stopped or self._stop.is_set()
            failing = False
        finally:
            report.next_sequence = sequence
            try:
                final = self._finish(spool, report, failing, ended=not stopped)
            finally:
                self._pump_stop.set()
                self._wake.set()
                pump.join(5)
                self._fill(report, spool)
                self._done = True  # answers arriving later (the transport closes) change nothing
                if own_spool:
                    with self._lock:
                        spool.close()
        report.extra["final_status"] = final
        return report

    def _encode(
        self, frame: SourceFrame, sequence: int, capture_time: float, report: CameraReport
    ) -> bytes | None:
        detections = frame.detections
        reasons = box_rejections(detections.xyxy, self.reference.image_size)
        if any(reasons):
            keep = np.array([reason is None for reason in reasons])
            for reason in reasons:
                if reason is not None:
                    report.boxes_rejected[reason] = report.boxes_rejected.get(reason, 0) + 1
            detections = _select(detections, keep)
            logger.debug("camera %s frame %d: dropped %d boxes (%s)", self.camera_id,
                         frame.frame, int((~keep).sum()), ", ".join(r for r in reasons if r))
        message = make_message(
            self.camera_id, sequence, capture_time, frame.frame, detections,
            self.reference, self.targeting, drop_hidden_feet=self.drop_hidden_feet,
        )
        payload = encode_message(message, self.plane_id)
        if len(payload) > self.max_bytes:
            report.frames_too_large += 1
            logger.warning(
                "camera %s frame %d: the message has %d bytes, more than the %d the matcher "
                "accepts; dropped (%d boxes)", self.camera_id, frame.frame, len(payload),
                self.max_bytes, len(message),
            )
            return None
        report.messages += 1
        report.detections += len(message)
        report.located += int(np.count_nonzero(message.colour[:, 2]))
        report.bytes += len(payload)
        return payload

    def _finish(self, spool: Spool, report: CameraReport, failing: bool = False,
                ended: bool = True) -> bool:
        """Wait for the broker (and the matcher); publish the final status. Returns whether
        the timestamped (final) "offline" was published. ``failing``: the source raised; wait
        a little for the broker, not for the matcher (the spool keeps the rest). ``ended``:
        False when the node was stopped before its source ended: its stream has not ended
        (a restart goes on with it), so its "offline" is not the final one."""
        stopping = self._stop.is_set() or failing
        deadline = time.monotonic() + (min(self.flush_timeout_s, STOP_FLUSH_S) if stopping
                                       else self.flush_timeout_s)
        reminded = time.monotonic()
        offline_since: float | None = None
        while self._refusal is None and time.monotonic() < deadline:
            counts = spool.counts()
            untaken = counts["waiting"] + counts["handed"]
            if not self._answers:
                # Handed over is not taken (NATS retries on its own): wait for the stream.
                untaken += self.transport.pending()
            if untaken == 0:
                break
            now = time.monotonic()
            connected = getattr(self.transport, "connected", True)
            offline_since = None if connected else (offline_since or now)
            if self._stop.is_set() and not stopping:
                # Stopped during the wait (a signal): the spool keeps what is not taken.
                stopping = True
                deadline = min(deadline, now + STOP_FLUSH_S)
            if stopping and offline_since is not None and now - offline_since >= STOP_OFFLINE_S:
                break  # no broker to take them: a stop does not wait for one
            if now - reminded >= 10.0 and not connected:
                reminded = now
                logger.warning("camera %s: waiting for %s to take %d messages",
                               self.camera_id, self._backbone, untaken)
            self._wake.set()
            if stopping:
                time.sleep(0.02)
            else:
                self._stop.wait(0.02)  # a stop cuts the wait short
        counts = spool.counts()
        all_handed = self._refusal is None and counts["waiting"] == 0 and counts["handed"] == 0
        if all_handed and not self._answers:
            all_handed = self.transport.flush(0.0)  # the stream took everything
        # Flushed: the broker acknowledged every message (later re-sends change nothing).
        self._flushed = all_handed
        stopping = stopping or self._stop.is_set()
        if (all_handed and self.confirm_timeout_s > 0 and not stopping):
            confirm_deadline = time.monotonic() + self.confirm_timeout_s
            while len(spool) and time.monotonic() < confirm_deadline and self._refusal is None:
                if self._stop.wait(0.02):
                    stopping = True  # stopped during the wait: what is unconfirmed stays
                    break
        # Nothing may follow the final "offline": stop the pump before publishing it.
        self._pump_stop.set()
        self._wake.set()
        final = ended and self._flushed and self._refusal is None and (
            self.confirm_timeout_s <= 0 or len(spool) == 0)
        if getattr(self.transport, "connected", True):
            self._announce("offline", final=final)
            if final:
                clear_will = getattr(self.transport, "clear_will", None)
                if clear_will is not None:
                    clear_will()
            remaining = max(0.5, deadline - time.monotonic())
            self.transport.flush(min(remaining, 2.0) if stopping else remaining)
        return final

    def _fill(self, report: CameraReport, spool: Spool) -> None:
        counts = spool.counts()
        unstored = 0
        pending_on = getattr(self.transport, "pending_on", None)
        if not self._answers and pending_on is not None:
            # Handed over is not taken (NATS): what the transport still holds is not stored.
            unstored = pending_on(self.topic)
        with self._lock:
            report.acknowledged = max(0, self._counts["acknowledged"] - unstored)
            report.confirmed = self._counts["confirmed"]
            report.refused_by_broker = self._counts["refused"]
            # Sent again, not queued again: the matcher's confirmations of the first copies
            # may empty the queue before it goes.
            report.resent = self._spool.taken_again
            report.rejected_by_matcher = dict(self._rejected_by_matcher)
            report.refusal = self._refusal
        report.unconfirmed = len(spool)
        report.dropped_from_spool = counts["dropped"]
        report.flushed = self._flushed and self._refusal is None
        report.confirmed_all = report.unconfirmed == 0
        if self._counts["already_spooled"]:
            report.extra["already_spooled"] = self._counts["already_spooled"]
        report.extra["unrouted"] = self._counts["unrouted"]
        # What the backbone did to this camera's publishes, where the transport counts it
        # (NATS: publishes held back at its per-camera stream limit, silent connections
        # made again); shown only when something happened.
        for name in ("subject_full_refusals", "silent_reconnects"):
            value = getattr(self.transport, name, 0)
            if isinstance(value, int) and value:
                report.extra[name] = value

    @property
    def _backbone(self) -> str:
        """What the transport's backbone is called in messages ("the MQTT broker")."""
        return str(getattr(self.transport, "backbone_name", "the broker"))

    # -- the pump ---------------------------------------------------------------------------

    def _pump(self) -> None:
        spool = self._spool
        pending = getattr(self.transport, "pending", lambda: 0)
        disconnected_since: float | None = None
        reminded = 0.0
        while not self._pump_stop.is_set():
            self._maybe_resend()
            if self._refusal is None:
                room = self.window - pending()
                if room > 0:
                    items = spool.take(min(room, 256))
                    for sequence, topic, payload in items:
                        if self._answers:
                            self.transport.publish(
                                topic, payload, qos=1,
                                on_result=functools.partial(self._on_result, sequence, topic),
                            )
                        elif self._marks_resends:
                            self.transport.publish(topic, payload, qos=1,
                                                   resend=self._resend_token(sequence))
                            self._on_result(sequence, topic, 0)
                        else:
                            self.transport.publish(topic, payload, qos=1)
                            self._on_result(sequence, topic, 0)
                    if items:
                        continue
            if not getattr(self.transport, "connected", True):
                now = time.monotonic()
                disconnected_since = disconnected_since or now
                if now - disconnected_since >= 30.0 and now - reminded >= _REMINDER_S:
                    reminded = now
                    logger.warning(
                        "camera %s: no connection to %s for %.0f s; %d messages wait in the "
                        "spool", self.camera_id, self._backbone, now - disconnected_since,
                        len(spool))
            else:
                disconnected_since = None
                if self._announce_when_connected and not self._online_published:
                    self._announce("online")
            self._wake.wait(0.1)
            self._wake.clear()

    # -- timing ------------------------------------------------------------------------------

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
            for frame in iterator:  # a stop ends the reading (a detector may be slow)
                if self._stop.is_set():
                    break
                pending.append(frame)
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
                if report.frames == 1:
                    self._say_first_wait(recorded, capture_time, delay)
                if delay > 0 and self._stop.wait(delay):
                    return
            yield frame, capture_time

    def _say_first_wait(self, recorded: float, capture_time: float, delay: float) -> None:
        """Say when the first paced frame goes out if that is not now: a recording that
        starts at 100 s replayed with ``--epoch now+5`` is silent for 105 s otherwise.

        Args:
            recorded: the first frame's recorded time (divided by the speed), seconds.
            capture_time: when it is due, seconds since the Unix epoch.
            delay: how long until then, seconds.
        """
        if delay <= _FIRST_WAIT_SAID_S:
            return
        due = time.strftime("%H:%M:%S", time.gmtime(capture_time))
        hint = ""
        if delay > _FIRST_WAIT_WARN_S and recorded > _FIRST_WAIT_SAID_S:
            hint = (
                f"; the recording starts at {recorded:g} s, so to start it at once give every "
                f"camera --epoch $(( $(date +%s) + 5 - {recorded:.0f} ))"
            )
        logger.log(
            logging.WARNING if delay > _FIRST_WAIT_WARN_S else logging.INFO,
            "camera %s: the first frame (recorded at %g s) is due at %s UTC (--epoch + its "
            "time), in %.0f s; nothing is sent before%s",
            self.camera_id, recorded, due, delay, hint,
        )


def _select(detections: Detections, keep: np.ndarray) -> Detections:
    return detections[keep]


def _chain(first: list[SourceFrame], rest: Iterator[SourceFrame]) -> Iterator[SourceFrame]:
    yield from first
    yield from rest
