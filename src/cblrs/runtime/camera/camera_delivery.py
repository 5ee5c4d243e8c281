"""The delivery side of a camera node (:class:`_CameraDelivery`, a part of
:class:`~cblrs.runtime.camera.camera_node.CameraNode`).

The broker's result for each publish (a refusal stops the node), the matcher's confirmations
(the spool forgets what is confirmed; a gap before a confirmed message is sent again), the
matcher's status (a new session: everything unconfirmed is sent again), the resend timer when
confirmations stall, and the node's own "online" announcements.
"""

from __future__ import annotations

import logging
from typing import Any

from cblrs.runtime.camera.camera_state import _CameraState
from cblrs.runtime.matcher.confirmations import decode_confirmation
from cblrs.runtime.transport.protocol import LOST, NO_MATCHING_SUBSCRIBERS, reason_text, refused
from cblrs.runtime.wire import (
    RejectedMessage,
    decode_status,
    encode_status,
)

logger = logging.getLogger("cblrs.runtime.camera.camera_node")
"""The node's logger: its parts log under the one name."""


MAX_RESEND_AFTER_S = 300.0


class _CameraDelivery(_CameraState):
    """Results, confirmations, matcher status and resends of a camera node."""

    def _resend_token(self, sequence: int) -> str | None:
        """None for the first publish of a message produced in this run; else a token no
        earlier publish of it carried (this process's start and a counter): a re-send, a
        message an earlier run left in the spool, which that run may have published, or one
        this run produced again (a replay restarted from its beginning) under a sequence an
        earlier run handed over: the stream would drop it as a duplicate, so the matcher
        would never see it again to confirm it."""
        with self._lock:
            if sequence in self._fresh:
                self._fresh.discard(sequence)
                if sequence >= getattr(self._spool, "handed_before", 0):
                    return None
            self._resends += 1
            return f"r{self._run_token}-{self._resends}"

    def _on_result(self, sequence: int, topic: str, reason: int) -> None:
        if self._done:
            return
        spool = self._spool
        if reason == LOST:
            spool.not_sent(sequence)
            return
        if refused(reason):
            spool.not_sent(sequence)
            with self._lock:
                self._counts["refused"] += 1
                first = self._refusal is None
                if first:
                    text = reason_text(reason)
                    self._refusal = (
                        f"the broker refused to take message {sequence} on {topic} ({text}): "
                        "check that this camera logs in as its own user and publishes for its "
                        "own id and plane"
                    )
            if first:
                logger.error("camera %s: %s; stopping", self.camera_id, self._refusal)
                self.stop()
            return
        spool.acknowledged(sequence)
        with self._lock:
            self._counts["acknowledged"] += 1
            first_unrouted = reason == NO_MATCHING_SUBSCRIBERS and not self._counts["unrouted"]
            if reason == NO_MATCHING_SUBSCRIBERS:
                self._counts["unrouted"] += 1
        if first_unrouted:
            logger.warning("camera %s: the broker has no subscriber for %s (no matcher has "
                           "subscribed yet); the spool keeps the messages until one confirms "
                           "them", self.camera_id, topic)

    def _maybe_resend(self) -> None:
        if not self._matcher_online:
            return
        spool = self._spool
        oldest = spool.oldest_acknowledged()
        if oldest is None:
            return
        now = spool.clock()
        quiet = now - max(self._last_confirmation, oldest)
        if quiet < self._resend_wait:
            return
        count = spool.requeue(acknowledged_before=now - self._resend_wait)
        if count:
            with self._lock:
                self._counts["resent"] += count
            logger.warning(
                "camera %s: the matcher confirmed nothing for %.0f s; sending %d unconfirmed "
                "messages again", self.camera_id, quiet, count)
            self._wake.set()
        self._resend_wait = min(2 * self._resend_wait, MAX_RESEND_AFTER_S)

    def _announce(self, state: str, final: bool = True) -> None:
        timestamp = self._clock() if (state == "online" or final) else None
        self.transport.publish(
            self.status_topic,
            encode_status(self.camera_id, state, role="camera", timestamp=timestamp),  # type: ignore[arg-type]
            qos=1,
            retain=True,
        )
        if state == "online":
            self._online_published = True

    def _on_connected(self, session_present: bool) -> None:
        if not self._pump_stop.is_set():
            self._announce("online")
            self._wake.set()

    def _on_stored(self, delivery: Any) -> None:
        delivery.ack()
        if self._done:
            return
        try:
            confirmation = decode_confirmation(delivery.payload)
        except RejectedMessage as error:
            logger.warning("camera %s: ignored a malformed confirmation: %s", self.camera_id,
                           error)
            return
        if confirmation.camera != self.camera_id:
            return
        stored = confirmation.stored_sequences()
        rejected = confirmation.rejected_sequences()
        answered = stored + [value for values in rejected.values() for value in values]
        top = max(answered) if answered else None
        top_acked = None if top is None else self._spool.acked_at(top)
        count = self._spool.confirm(stored)
        rejected_count = 0
        for reason, sequences in rejected.items():
            dropped = self._spool.confirm(sequences)
            rejected_count += dropped
            if dropped:
                with self._lock:
                    self._rejected_by_matcher[reason] += dropped
                logger.warning("camera %s: the matcher rejected %d messages (%s)",
                               self.camera_id, dropped, reason)
        # Only where "acknowledged" means the broker has it (MQTT answers; a NATS transport
        # retries on its own and its matcher may see re-deliveries out of order), and only
        # while the pump still sends.
        if (top is not None and top_acked is not None and self._answers
                and not self._pump_stop.is_set()):
            gaps = self._spool.requeue_gaps(below=top, acknowledged_before=top_acked)
            if gaps:
                with self._lock:
                    self._counts["resent"] += gaps
                logger.warning(
                    "camera %s: the matcher confirmed message %d but not %d earlier ones the "
                    "broker had acknowledged (dropped on the way); sending them again",
                    self.camera_id, top, gaps)
                self._wake.set()
        with self._lock:
            self._counts["confirmed"] += count
        self._last_confirmation = self._spool.clock()
        self._resend_wait = self.resend_after_s
        self._matcher_online = True

    def _on_matcher_status(self, delivery: Any) -> None:
        delivery.ack()
        if self._done:
            return
        try:
            status = decode_status(delivery.payload)
        except RejectedMessage:
            return
        if status.role != "matcher":
            return
        if status.state == "online":
            self._matcher_online = True
            # A live "online" with a new session: the broker held nothing for this matcher
            # until now. A retained one is history (the session exists since; what this
            # camera sends now reaches it, and spooled messages of earlier runs go anyway).
            if status.session_present is False and not getattr(delivery, "retain", False):
                # The broker held nothing for this matcher: whatever it has not confirmed
                # must be sent again.
                count = self._spool.requeue()
                if count:
                    with self._lock:
                        self._counts["resent"] += count
                    logger.info("camera %s: matcher %s started a new session; sending %d "
                                "unconfirmed messages again", self.camera_id, status.client,
                                count)
                self._wake.set()
        else:
            self._matcher_online = False
