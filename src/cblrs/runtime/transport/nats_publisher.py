"""The publisher of a NATS transport with its acknowledgement pipeline (:class:`_NatsPublisher`,
a part of :class:`~cblrs.runtime.transport.nats_transport.NatsTransport`).

Stream publishes leave in order, up to ``publish_window`` awaiting the stream's answer; one
not answered in time, refused for a moment (no stream leader, a camera subject full) or failed
on a lost connection goes again with its ``Nats-Msg-Id``, in its order, before anything newer.
Publishes left unanswered also probe the connection (:meth:`_NatsPublisher._probe_connection`):
one that answers no ping is made again.
"""

from __future__ import annotations

import asyncio
import bisect
import json
import logging
import time
from dataclasses import dataclass
from typing import Any

from cblrs.runtime.transport.nats_streams import _NatsStreams
from cblrs.runtime.transport.nats_subjects import _classify

logger = logging.getLogger("cblrs.runtime.transport.nats_transport")
"""The transport's logger: its parts log under the one name (levels set on it, as the
dashboard does, hold for all of them)."""

_SUBJECT_FULL = 10077
"""JetStream's error code for a publish refused by ``max_msgs_per_subject`` with
``discard_new_per_subject`` (nats-server 2.15.1 answers ``code`` 503 with it)."""


class _NatsPublisher(_NatsStreams):
    """The stream publishes of a NATS transport, their answers and their retries."""

    def _publish_core(self, subject: str, data: bytes) -> None:
        if self._nc is not None:
            task = asyncio.ensure_future(self._nc.publish(subject, data))
            self._core_publishes.add(task)
            task.add_done_callback(self._core_publishes.discard)

    def _enqueue_publish(self, subject: str, data: bytes, identifier: str | None) -> None:
        self._outgoing.append(_Outgoing(subject, data, identifier, self._next_order))
        self._next_order += 1
        assert self._publish_wake is not None
        self._publish_wake.set()

    async def _publish_loop(self) -> None:
        """Send stream publishes in order, up to ``publish_window`` awaiting their answer;
        send again, in their order and before anything newer, those that failed."""
        settings = self.settings
        wake = self._publish_wake
        assert wake is not None
        counter = 0
        # Not "while True": Python 3.11's wait_for can swallow a cancellation that arrives
        # as the event is set, and close() must end this loop all the same.
        while not self._closing:
            now = time.monotonic()
            expired = [token for token, item in self._in_flight.items()
                       if now - item.sent_at > settings.publish_timeout_s]
            for token in expired:
                item = self._in_flight.pop(token)
                self._abandoned[token] = item
                self._retry(item, "no acknowledgement in time")
            if expired and (self._probe is None or self._probe.done()):
                self._probe = asyncio.ensure_future(self._probe_connection())
            # After a failure, nothing is sent again until every publish in flight is
            # answered or given up: then all that failed go again in their order, before
            # anything newer (a later publish stored first would overtake them).
            while (len(self._in_flight) < settings.publish_window and now >= self._retry_at
                   and (self._resend or self._outgoing) and self._nc.is_connected
                   and not (self._resend and self._in_flight)):
                item = self._resend.pop(0) if self._resend else self._outgoing.popleft()
                if item.done:
                    continue
                if item.subject.lower() in self.refused_subjects:  # permissions do not change
                    self._finish(item, refused=f"the login {settings.username} may not publish "
                                 f"on {item.subject}")
                    continue
                if settings.manages:
                    kind = _classify(item.subject, self._site)
                    if kind is not None:
                        try:
                            await self._resolve_stream(*kind)
                        except Exception as error:
                            self._retry(item, str(error))
                            break
                token = str(counter)
                counter += 1
                headers = {"Nats-Msg-Id": item.identifier} if item.identifier else None
                item.sent_at = time.monotonic()
                self._in_flight[token] = item
                try:
                    await self._nc.publish(item.subject, item.data, reply=self._ack_prefix + token,
                                           headers=headers)
                except Exception as error:  # reconnecting: nats-py refuses while closed
                    self._in_flight.pop(token, None)
                    self._retry(item, str(error) or type(error).__name__)
                    break
            wake.clear()
            waits = [1.0]
            if self._in_flight:
                oldest = min(item.sent_at for item in self._in_flight.values())
                waits.append(oldest + settings.publish_timeout_s - time.monotonic())
            if self._resend and self._retry_at > time.monotonic():
                waits.append(self._retry_at - time.monotonic())
            try:
                await asyncio.wait_for(wake.wait(), max(0.001, min(waits)))
            except TimeoutError:
                pass

    async def _probe_connection(self) -> None:
        """After publishes went unanswered: does the connection still carry anything?

        A stream without a leader leaves publishes unanswered on a healthy connection, and a
        ping shows that one is healthy. But a connection nats-py calls up can carry nothing
        (a stalled TLS write, a middlebox that dropped the flow): its own pings notice only
        after minutes (two missed, two minutes apart), while every publish waits. Without an
        answer to a ping within the publish timeout, the connection is dropped and made
        again (nats-py resubscribes; what was not acknowledged goes again in its order).
        """
        nc = self._nc
        if nc is None or self._closing or not nc.is_connected:
            return
        timeout = self.settings.publish_timeout_s
        flusher = getattr(nc, "_flusher_task", None)
        if flusher is None or not flusher.done():
            try:
                await nc.flush(timeout=timeout)
                return
            except Exception:  # nats-py's FlushTimeoutError, or the connection closing
                if self._closing or nc is not self._nc or not nc.is_connected:
                    return
        self.silent_reconnects += 1
        logger.warning("%s: the NATS connection is up but answered no ping within %g s "
                       "(publishes unanswered): connecting again", self.client_id, timeout)
        await nc.force_reconnect()

    async def _on_publish_answer(self, msg: Any) -> None:
        """A stream's answer to one of our publishes (or the servers' "no responders")."""
        token = msg.subject[len(self._ack_prefix):]
        item = self._in_flight.pop(token, None) or self._abandoned.pop(token, None)
        if item is None or item.done:
            return
        headers = msg.headers or {}
        if headers.get("Status") == "503" or not msg.data:
            if item.subject not in self._warned_no_stream:
                self._warned_no_stream.add(item.subject)
                logger.warning("%s: no NATS stream answered a publish on %s (no stream "
                               "leader at the moment, or the plane is not prepared: cblrs "
                               "matcher --prepare with the admin's login); sending it again",
                               self.client_id, item.subject)
            self._retry(item, "no stream answered")
            return
        try:
            answer = json.loads(msg.data)
        except ValueError:
            self._retry(item, "an unreadable answer")
            return
        error = answer.get("error")
        if error:
            code = error.get("code") or 0
            if error.get("err_code") == _SUBJECT_FULL:
                self._subject_full(item)
            elif code == 503 or code >= 500:
                self._retry(item, error.get("description", "no stream leader"))
            else:
                self._finish(item, refused=error.get("description", str(error)))
            return
        if item.resent and not answer.get("duplicate") and item.order < self._stored_order:
            self.reordered += 1
            logger.warning("%s: a publish on %s sent again was stored after a later one "
                           "(%d so far)", self.client_id, item.subject, self.reordered)
        self._stored_order = max(self._stored_order, item.order)
        self._retry_delay = 0.05
        if item.subject in self._full_subjects:
            self._full_subjects.discard(item.subject)
            logger.warning("%s: the NATS stream stores publishes on %s again", self.client_id,
                           item.subject)
        self._finish(item)

    def _subject_full(self, item: _Outgoing) -> None:
        """The stream refused ``item``: its subject holds ``max_msgs_per_subject`` messages.
        Counted, warned once per subject until one is stored again, and sent again later
        in its order (the camera's spool keeps what is not confirmed)."""
        self.subject_full_refusals += 1
        if item.subject not in self._full_subjects:
            self._full_subjects.add(item.subject)
            logger.error("%s: the NATS stream refused a publish on %s: the subject holds its "
                         "maximum of messages (max_msgs_per_subject; this camera published "
                         "more than its share, or a forged reply filled it, see "
                         "docs/security.md); sending it again until the stream has room",
                         self.client_id, item.subject)
        self._retry(item, "maximum messages per subject")

    def _retry(self, item: _Outgoing, reason: str) -> None:
        """Send ``item`` again after a pause, before anything newer and in its order."""
        if item.done:
            return
        logger.debug("%s: publish on %s sent again: %s", self.client_id, item.subject, reason)
        item.resent = True
        if item not in self._resend:
            bisect.insort(self._resend, item, key=lambda entry: entry.order)
        self._retry_at = time.monotonic() + self._retry_delay
        self._retry_delay = min(1.0, self._retry_delay * 2)
        if self._publish_wake is not None:
            self._publish_wake.set()

    def _finish(self, item: _Outgoing, refused: str | None = None) -> None:
        if item.done:
            return
        item.done = True
        if item.resent and item in self._resend:
            self._resend.remove(item)
        if refused is not None:
            self.refused_publishes += 1
            logger.warning("%s: the NATS servers refused a publish on %s for good: %s",
                           self.client_id, item.subject, refused)
        with self._condition:
            self._pending -= 1
            self._pending_by_subject[item.subject] -= 1
            if not self._pending_by_subject[item.subject]:
                del self._pending_by_subject[item.subject]
            self._condition.notify_all()
        if self._publish_wake is not None:
            self._publish_wake.set()


@dataclass(eq=False)
class _Outgoing:
    """One stream publish: its place in this client's order, and whether it is settled."""

    subject: str
    data: bytes
    identifier: str | None
    order: int
    sent_at: float = 0.0
    resent: bool = False
    done: bool = False
