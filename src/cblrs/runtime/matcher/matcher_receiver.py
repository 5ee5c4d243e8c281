"""The receiver of a :class:`~cblrs.runtime.matcher.matcher_service.MatcherService`
(:class:`_Receiver`): steps 1-3 of the service, on its own thread.

The transport's thread queues deliveries; the receiver takes what has arrived in batches:
validates each (a rejection is counted and acknowledged), stores the batch in one inbox
transaction, acknowledges it, confirms the stored sequences to the cameras and adds the
messages to the ordering buffer. Camera status messages (online, offline) go to the ordering
too. Its retention thread keeps the database within its limits.
"""

from __future__ import annotations

import functools
import logging
import time
from collections import Counter
from typing import Any

from cblrs.runtime.matcher.confirmations import peek_sequence
from cblrs.runtime.matcher.matcher_state import _MatcherState
from cblrs.runtime.matcher.retention import apply_retention
from cblrs.runtime.matcher.store_rows import InboxEntry
from cblrs.runtime.matcher.store_schema import LATE, PENDING
from cblrs.runtime.transport.topics import TopicError, parse_detections_topic, parse_status_topic
from cblrs.runtime.wire import RejectedMessage, decode_status

logger = logging.getLogger("cblrs.runtime.matcher.matcher_service")
"""The service's logger: its parts log under the one name."""


class _Receiver(_MatcherState):
    """The receiver thread of a matcher service (and its transport callbacks)."""

    def _on_detections(self, delivery: Any) -> None:
        self._inbox.append(("detections", delivery, self._wall_clock()))
        self._arrived.set()

    def _on_status(self, delivery: Any) -> None:
        self._inbox.append(("status", delivery, self._wall_clock()))
        self._arrived.set()

    def _work(self) -> None:
        """Receiver thread: store and acknowledge deliveries, buffer them for the tracker."""
        try:
            while not self._stop.is_set():
                if not self._receiving.is_set():  # no verified lease: acknowledge nothing
                    self._receiving.wait(0.2)
                    continue
                self._arrived.wait(0.2)
                self._arrived.clear()  # before emptying the inbox, so no arrival is missed
                while self._receiving.is_set() and self._handle():
                    self._wake.set()
                    self._send_confirmations()
                    if self._stop.is_set():
                        break
                self._send_confirmations()
            # Stopping: with a flush, also store what is queued. Anything left is
            # unacknowledged, so the broker delivers it again later.
            while (self._flush_requested.is_set() and self._failure is None
                   and self._receiving.is_set() and self._handle()):
                pass
        except BaseException as error:  # surfaced by stop()
            self._fail(error, "receiver")
        finally:
            self._received_all.set()
            self._wake.set()

    def _handle(self) -> bool:
        """Store, acknowledge and buffer the next batch of deliveries; False if none."""
        # Taking the batch, late marking, storing and buffering happen as one step against
        # the release of groups (see the module docstring) and ``drained``.
        with self._state_lock:
            count = min(len(self._inbox), self.batch_size)
            if not count:
                return False
            self._handle_locked([self._inbox.popleft() for _ in range(count)])
            return True

    def _handle_locked(self, batch: list[tuple[str, Any, float]]) -> None:
        started = time.perf_counter()
        now = self.clock()
        counters: Counter[str] = Counter()
        accepted: list[tuple[InboxEntry, str, float]] = []
        acknowledge = []
        rejected: list[tuple[str, int, str]] = []
        for kind, delivery, received_at in batch:
            acknowledge.append(delivery)
            if kind == "status":
                self._status(delivery, now)
                continue
            if not delivery.payload:
                # An empty retained publish removes a retained message (a camera clearing its
                # detections topic); it is never a message.
                continue
            if delivery.retain and delivery.topic not in self._retained_warned:
                self._retained_warned.add(delivery.topic)
                logger.warning(
                    "plane %d: a retained message sits on %s (some client published with "
                    "retain); every new subscription receives it again. It is stored once "
                    "(duplicates are ignored); `cblrs camera` removes it when it starts.",
                    self.plane_id, delivery.topic)
            self._last_delivery = now
            counters["received"] += 1
            try:
                plane_id, camera = _parse_topic(delivery.topic)
                wire = self.policy.decode_wire(
                    delivery.payload, topic_camera=camera, now=received_at, topic_plane=plane_id
                )
            except TopicError:
                counters["rejected.bad_topic"] += 1
                self._rejections.log(logging.WARNING, "bad_topic",
                                     "plane %d: rejected a message on %s: not a detections "
                                     "topic", self.plane_id, delivery.topic)
                continue
            except RejectedMessage as error:
                reason = error.reason.value
                counters[f"rejected.{reason}"] += 1
                self._rejections.log(logging.WARNING, reason,
                                     "plane %d: rejected a message on %s (%s): %s",
                                     self.plane_id, delivery.topic, reason, error)
                sequence = peek_sequence(delivery.payload, camera)
                if sequence is not None:
                    rejected.append((camera, sequence, reason))
                continue
            late = self._orderer.is_late(wire.timestamp)
            accepted.append((InboxEntry.from_wire(wire), LATE if late else PENDING, received_at))
        inserted = self.store.insert_messages(accepted, counters)
        if counters.get("conflicts"):
            self._rejections.log(
                logging.ERROR, "conflicts",
                "plane %d: %d messages repeat a stored camera and sequence number with other "
                "content (another run of a camera reusing its numbers: give it another "
                "--first-sequence); the stored ones are kept, these are counted as conflicts",
                self.plane_id, counters["conflicts"])
        # Acknowledge only now: everything above is durably stored (or rejected on purpose).
        for delivery in acknowledge:
            delivery.ack()
        for entry, _, _ in accepted:  # new or duplicates: stored either way
            self._confirmations.add_stored(entry.camera_id, entry.sequence)
        for camera, sequence, reason in rejected:
            self._confirmations.add_rejected(camera, sequence, reason)
        self.reporter.stored(batch, accepted, inserted, counters, time.perf_counter() - started)
        stored = []
        for (entry, status, _), new in zip(accepted, inserted, strict=True):
            if not new:
                continue
            stored.append(entry)
            self._active_this_run.add(entry.camera_id)
            if status == PENDING:
                self._orderer.add(entry, now)
            else:
                self._orderer.heard(entry.camera_id, now)
                if self.retrack is not None:
                    self._late_at = now
        if self.observer is not None and hasattr(self.observer, "on_stored") and stored:
            self.observer.on_stored(stored, self._wall_clock())

    def _retain(self) -> None:
        """Retention thread: apply the retention policy every ``interval_s``."""
        policy = self.retention
        if policy is None or not policy.enabled:
            return
        try:
            while not self._stop.wait(policy.interval_s):
                apply_retention(self.store, policy, self._wall_clock())
        except BaseException as error:  # surfaced by stop(): a store that fails, fails
            self._fail(error, "retention")

    def _send_confirmations(self, force: bool = False) -> None:
        """Publish the buffered confirmations, at most every ``confirm_interval_s``."""
        now = time.monotonic()
        if not force and now - self._last_confirmation < self.confirm_interval_s:
            return
        if not self._confirmations:
            return
        self._last_confirmation = now
        for topic, payload in self._confirmations.take():
            try:
                self.transport.publish(topic, payload, qos=1)
            except Exception as error:  # a camera sends again what it does not hear about
                logger.warning("plane %d: could not publish confirmations on %s: %s",
                               self.plane_id, topic, error)

    def _status(self, delivery: Any, now: float) -> None:
        try:
            plane_id, camera = parse_status_topic(delivery.topic)
            status = decode_status(delivery.payload)
        except (TopicError, RejectedMessage) as error:
            logger.debug("ignored status on %s: %s", delivery.topic, error)
            return
        if camera not in self._offline or plane_id != self.plane_id:
            return
        self.reporter.status(camera, status.state == "online")
        if status.state == "online":
            self._offline[camera] = self._final_offline[camera] = False
            self._offline_at[camera] = None
            self._active_this_run.add(camera)
            self._orderer.set_offline(camera, False)
            self._orderer.heard(camera, now)
        elif status.timestamp is None:
            # A last will (no timestamp): the connection dropped — a crash, or a broker
            # restart. It does not say the stream ended, so ordering keeps waiting for the
            # camera's messages (bounded by the silence window).
            pass
        else:
            # The camera's own "offline" at the end of its stream: nothing more will come.
            self._final_offline[camera] = True
            self._offline_at[camera] = status.timestamp
            # A retained one older than this service is history (the end of an earlier
            # replay): the camera may be about to start again, so ordering still waits.
            stale = bool(getattr(delivery, "retain", False)) and (
                status.timestamp < self._started_at
            )
            if not stale:
                self._offline[camera] = True
                self._orderer.set_offline(camera, True)
        logger.info("plane %d: camera %s is %s", self.plane_id, camera, status.state)


@functools.lru_cache(maxsize=4096)
def _parse_topic(topic: str) -> tuple[int, str]:
    """:func:`parse_detections_topic`, cached: a plane has few cameras, hence few topics."""
    return parse_detections_topic(topic)
