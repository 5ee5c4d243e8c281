"""The consumer side of a NATS transport (:class:`_NatsConsumer`, a part of
:class:`~cblrs.runtime.transport.nats_transport.NatsTransport`).

Plain NATS subscriptions, and the durable pull consumer that serves the subscriptions falling
in a plane's stream: its setup (created by the admin, reset by a runtime login to replay or to
deliver again what was handed out and not acknowledged), the pull requests that keep it
delivering, the deliveries (flagged ``duplicate`` or ``retain``, held while the lease is not
renewed), whether it has caught up, and the acknowledgements, sent in batches by the loop.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import time
from dataclasses import replace
from typing import Any

from cblrs.runtime.transport.nats_streams import _NatsStreams
from cblrs.runtime.transport.nats_subjects import (
    LEGACY_DETECTIONS_STREAM,
    LEGACY_TRACKS_STREAM,
    _classify,
    site_subject,
    site_topic,
    stream_subjects,
)
from cblrs.runtime.transport.protocol import TransportError, _Incoming
from cblrs.runtime.transport.topics import topic_matches

logger = logging.getLogger("cblrs.runtime.transport.nats_transport")
"""The transport's logger: its parts log under the one name (levels set on it, as the
dashboard does, hold for all of them)."""

_GIVE_UP_S = 120.0
"""How long the consumer's restart or state may stay unanswerable before the transport goes
on without it (a cluster still recovering answers within that; a refusal never does)."""


class _NatsConsumer(_NatsStreams):
    """The subscriptions and the durable consumer of a NATS transport."""

    async def _subscribe_core(self, topic_filter: str) -> None:
        site = self._site

        async def deliver(msg: Any) -> None:
            topic = site_topic(msg.subject, site)
            if not topic_matches(topic_filter, topic):  # moved here (kept its own subject)
                self._moved(topic)
                return
            self._handlers.dispatch(_Incoming(topic, msg.data, False, False, 0, _no_ack,
                                              (topic_filter,)))

        subject = site_subject(topic_filter, site)
        self._core[topic_filter] = await self._nc.subscribe(subject, cb=deliver)
        try:
            # Two round trips: the servers' -ERR for a refused subscription was seen after
            # the first PONG in ~4 % of tries here, never after the second (1500 tries).
            for _ in range(2):
                await self._nc.flush(timeout=self.settings.connect_timeout_s)
        except Exception:  # the refusal is still logged when the -ERR comes
            return
        if subject.lower() in self.refused_subscriptions:
            raise TransportError(
                f"{self.client_id}: the NATS servers refused the subscription to {subject}: "
                f"the login {self.settings.username} may not read it."
            )

    async def _start_consumer(self) -> None:
        # optional extra: pip install cblrs[nats]
        from nats.js.api import AckPolicy, ConsumerConfig, DeliverPolicy
        from nats.js.errors import NotFoundError

        assert self.durable is not None
        subjects = sorted({site_subject(topic_filter, self._site)
                           for topic_filter in self._bound})
        planes = {kind[1] for subject in subjects if (kind := _classify(subject, self._site))}
        if len(planes) != 1:
            raise TransportError(
                f"{self.client_id}: the consumer {self.durable} serves one plane's stream; "
                f"its subscriptions span planes {sorted(planes)}."
            )
        plane = planes.pop()
        stream = await self._resolve_stream(self.consume, plane)
        self._consumer_stream = stream
        if self.settings.manages:  # the admin's --prepare: the plane's tracks stream too
            await self._resolve_stream("tracks", plane)
        # A plane's own stream needs no filter when the subscriptions cover it; the legacy
        # stream of every plane does.
        filters: list[str] | None = subjects
        if stream not in (LEGACY_DETECTIONS_STREAM, LEGACY_TRACKS_STREAM) and \
                set(subjects) == set(stream_subjects(stream, plane, self._site)):
            filters = None
        self._consumer_config = ConsumerConfig(
            name=self.durable, durable_name=self.durable, ack_policy=AckPolicy.EXPLICIT,
            deliver_policy=DeliverPolicy.ALL, ack_wait=self.settings.ack_wait_s,
            max_ack_pending=self.settings.max_ack_pending, max_deliver=-1,
            filter_subjects=filters if filters and len(filters) > 1 else None,
            filter_subject=filters[0] if filters and len(filters) == 1 else None,
        )
        if not self.settings.manages:
            await self._check_consumer(stream)
        else:
            if self.replay:
                try:
                    await self._js.delete_consumer(stream, self.durable)
                    logger.info("%s: consumer %s reset to replay the stream", self.client_id,
                                self.durable)
                except NotFoundError:
                    pass
                self.replay = False
            else:
                # What an earlier holder was handed and never acknowledged (it died, or the
                # deliveries died with a server) comes now, not after ack_wait.
                try:
                    await self._redeliver_unacknowledged()
                except Exception as error:  # e.g. not permitted: they come after ack_wait
                    logger.warning("%s: could not restart the consumer %s at its "
                                   "acknowledgement floor (%s); unacknowledged messages come "
                                   "again after %g s", self.client_id, self.durable,
                                   error or type(error).__name__, self.settings.ack_wait_s)
            try:
                await self._js.add_consumer(stream, self._consumer_config)
            except Exception as error:
                raise TransportError(
                    f"{self.client_id}: cannot set up the consumer {self.durable}: {error}."
                ) from None
        self._resume_at = None
        self._last_delivery = 0
        self._pull_wake = asyncio.Event()
        self._pull_task = asyncio.get_running_loop().create_task(self._pull())

    async def _check_consumer(self, stream: str) -> None:
        """Without the right to create consumers: the admin's consumer must exist; a replay
        resets it to the stream's first message, and otherwise a reset to its
        acknowledgement floor hands out again at once what an earlier holder was handed and
        never acknowledged (resetting is the one management call a matcher may make on its
        own consumer: it cannot point the consumer anywhere else)."""
        from nats.js.errors import NotFoundError

        assert self.durable is not None
        try:
            info = await self._js.consumer_info(stream, self.durable,
                                                timeout=self.settings.connect_timeout_s)
        except NotFoundError:
            raise TransportError(
                f"{self.client_id}: the NATS consumer {self.durable} of stream {stream} does "
                "not exist; the backbone's admin creates the plane's streams and consumer "
                "(cblrs matcher --prepare with the admin's login)."
            ) from None
        except Exception as failure:
            raise TransportError(
                f"{self.client_id}: cannot read the NATS consumer {self.durable} of stream "
                f"{stream} ({self._denial_or(failure)})."
            ) from None
        if self.replay:
            await self._reset_consumer(stream, 1, "replay the stream")
            self.replay = False
        elif info.num_ack_pending:
            logger.info("%s: %d messages were handed out and not acknowledged; delivering "
                        "them again", self.client_id, info.num_ack_pending)
            await self._reset_consumer(stream, None, "deliver them again")

    async def _reset_consumer(self, stream: str, sequence: int | None, why: str) -> None:
        """``$JS.API.CONSUMER.RESET``: to stream ``sequence``, or (None) to one above the
        acknowledgement floor (nats-server 2.14 and later)."""
        assert self.durable is not None
        request = b"" if sequence is None else json.dumps({"seq": sequence}).encode()
        problem: dict[str, Any] | None
        try:
            answer = await self._nc.request(
                f"$JS.API.CONSUMER.RESET.{stream}.{self.durable}", request,
                timeout=self.settings.connect_timeout_s)
            problem = json.loads(answer.data or b"{}").get("error")
        except Exception as failure:
            problem = {"description": self._denial_or(failure)}
        if problem:
            raise TransportError(
                f"{self.client_id}: cannot reset the consumer {self.durable} to {why}: "
                f"{problem.get('description', problem)}."
            )
        logger.info("%s: consumer %s reset to %s", self.client_id, self.durable, why)

    async def _redeliver_unacknowledged(self) -> None:
        """Restart the durable consumer at its first unacknowledged message.

        JetStream counts a message as delivered once it has sent it: a message in flight to
        a matcher that died, or lost with the server that carried it, comes again only after
        ``ack_wait`` (30 s), behind everything newer, so the matcher would hold it late. Here
        the consumer is created anew from its acknowledgement floor: every message after the
        floor comes again at once, in stream order (the matcher's store recognises those it
        already holds). Called before the first pull and after every reconnection; without
        unacknowledged messages it changes nothing.
        """
        # optional extra: pip install cblrs[nats]
        from nats.js.api import DeliverPolicy
        from nats.js.errors import NotFoundError

        assert self.durable is not None
        if self._resume_at is None:
            try:
                info = await self._js.consumer_info(self._consumer_stream, self.durable)
            except NotFoundError:
                if self._floor is None:
                    return  # a new consumer: add_consumer delivers from the first message
                info = None  # deleted here before, its creation failed: create it now
            if info is not None:
                if not info.num_ack_pending:
                    return
                self._floor = info.ack_floor.stream_seq + 1
                logger.info("%s: %d messages were handed out and not acknowledged; "
                            "delivering again from stream sequence %d", self.client_id,
                            info.num_ack_pending, self._floor)
                try:
                    await self._js.delete_consumer(self._consumer_stream, self.durable)
                except NotFoundError:
                    pass
            self._resume_at = self._floor
        else:
            try:
                await self._js.delete_consumer(self._consumer_stream, self.durable)
            except NotFoundError:
                pass
        # Kept until the consumer exists again: a failure between the deletion and the
        # creation must not make the next attempt start from the stream's first message.
        self._consumer_config = replace(
            self._consumer_config, deliver_policy=DeliverPolicy.BY_START_SEQUENCE,
            opt_start_seq=self._resume_at)

    async def _check_caught_up(self) -> None:
        """Nothing came for a while: ask the consumer whether it has anything left."""
        try:
            info = await self._js.consumer_info(self._consumer_stream, self.durable)
        except Exception as error:  # not ready yet: ask again at the next idle beat
            logger.debug("%s: consumer info: %s", self.client_id, error)
            self._check_failing_since = self._check_failing_since or time.monotonic()
            if time.monotonic() - self._check_failing_since > _GIVE_UP_S:
                # Unanswerable (e.g. not permitted): connected counts as caught up.
                logger.warning("%s: cannot ask the consumer %s what it holds (%s); a silent "
                               "camera is given up by the window alone", self.client_id,
                               self.durable, error or type(error).__name__)
                self._caught_up = True
                self._check_failing_since = None
            return
        self._check_failing_since = None
        if not self._redeliver:
            self._caught_up = info.num_pending == 0

    async def _pull(self) -> None:
        """Keep pull requests outstanding on the durable consumer; deliver what comes."""
        nc, settings = self._nc, self.settings
        inbox = nc.new_inbox()
        await nc.subscribe(inbox, cb=self._on_pulled)
        request_subject = f"$JS.API.CONSUMER.MSG.NEXT.{self._consumer_stream}.{self.durable}"
        batch = max(1, settings.pull_batch)
        expires_s = max(5.0, 5 * settings.heartbeat_s)
        assert self._pull_wake is not None
        failing_since: float | None = None
        while not self._closing and not self.lease_lost:
            if self._redeliver and nc.is_connected:
                try:
                    if not settings.manages:  # a runtime login resets its own consumer
                        await self._reset_consumer(self._consumer_stream, None,
                                                   "deliver again what was lost on the way")
                        self._last_delivery = 0
                    else:
                        await self._redeliver_unacknowledged()
                        if self._resume_at is not None:
                            await self._js.add_consumer(self._consumer_stream,
                                                        self._consumer_config)
                            self._resume_at = None
                            self._last_delivery = 0
                    self._redeliver = False
                except asyncio.CancelledError:
                    raise
                except Exception as error:  # the cluster is not ready yet: pull nothing
                    logger.debug("%s: consumer not restarted yet: %s", self.client_id, error)
                    failing_since = failing_since or time.monotonic()
                    if (self._resume_at is None
                            and time.monotonic() - failing_since > _GIVE_UP_S):
                        # Never deleted: the consumer still serves, only later.
                        logger.warning("%s: could not restart the consumer %s for %.0f s "
                                       "(%s); unacknowledged messages come again after %g s",
                                       self.client_id, self.durable, _GIVE_UP_S,
                                       error or type(error).__name__, settings.ack_wait_s)
                        self._redeliver = False
                    else:
                        await asyncio.sleep(settings.reconnect_wait_s)
                        continue
                failing_since = None
            now = time.monotonic()
            if now - self._last_activity > 3 * settings.heartbeat_s:
                self._outstanding = 0  # nothing, not even heartbeats: the requests are gone
            if self._outstanding <= batch // 2 and nc.is_connected:
                request = {"batch": batch, "expires": int(expires_s * 1e9),
                           "idle_heartbeat": int(settings.heartbeat_s * 1e9)}
                try:
                    await nc.publish(request_subject, json.dumps(request).encode(), reply=inbox)
                    self._outstanding += batch
                    self._last_activity = now
                except Exception as error:
                    logger.debug("%s: pull request failed: %s", self.client_id, error)
            self._pull_wake.clear()
            try:
                await asyncio.wait_for(self._pull_wake.wait(), settings.heartbeat_s)
            except TimeoutError:
                if not self._caught_up and nc.is_connected and not self._redeliver:
                    await self._check_caught_up()

    async def _on_pulled(self, msg: Any) -> None:
        self._last_activity = time.monotonic()
        headers = msg.headers
        if headers and not msg.data and "Status" in headers:
            status = headers.get("Status")
            if status != "100":  # 404/408 request done, 409 consumer changed: ask again
                pending = int(headers.get("Nats-Pending-Messages", 0) or 0)
                self._outstanding = max(0, self._outstanding - pending) if pending else 0
                if status == "409":
                    logger.info("%s: pull request ended: %s", self.client_id,
                                headers.get("Description"))
                assert self._pull_wake is not None
                self._pull_wake.set()
            return
        self._outstanding -= 1
        if self._outstanding <= self.settings.pull_batch // 2:
            self._pull_wake.set()  # type: ignore[union-attr]
        reply = msg.reply
        delivered, stamp, consumer_sequence, pending = _ack_metadata(reply)
        if self._last_delivery and consumer_sequence > self._last_delivery + 1:
            # Deliveries in between were lost on the way (a server or route died): they
            # would come again only after ack_wait, behind newer ones.
            logger.info("%s: deliveries %d-%d of the consumer were lost on the way",
                        self.client_id, self._last_delivery + 1, consumer_sequence - 1)
            self._redeliver = True
            self._caught_up = False
            self._pull_wake.set()  # type: ignore[union-attr]
        elif not self._redeliver:
            self._caught_up = pending == 0
        self._last_delivery = consumer_sequence
        topic = site_topic(msg.subject, self._site)
        if not any(topic_matches(topic_filter, topic) for topic_filter in self._bound):
            # Not this consumer's: moved into its stream by a pull that named one of the
            # stream's subjects as its reply (nats-server never checks a reply subject; the
            # stream keeps the message's own subject). Ended, never handed out again.
            self._moved(topic)
            if self._nc is not None and reply:
                await self._nc.publish(reply, b"+TERM")
            return
        retain = topic.endswith("/status") and stamp < self._connected_at
        if self.lease_lost:
            return
        item = _Incoming(topic, msg.data, delivered > 1, retain, 1,
                         functools.partial(self._queue_ack, reply), None)
        if self._lease_paused:
            self._held.append(item)
        else:
            self._handlers.dispatch(item)

    def _moved(self, topic: str) -> None:
        self.moved_messages += 1
        if self.moved_messages & (self.moved_messages - 1) == 0:  # 1st, 2nd, 4th, ...
            logger.warning("%s: dropped %d messages that came under a subject not subscribed "
                           "(the last on %s): another login moved them here",
                           self.client_id, self.moved_messages, topic)

    def _queue_ack(self, reply: str) -> None:
        """Acknowledge (any thread): queued, sent in batches by the loop."""
        if self.lease_lost or self._loop is None:
            return
        self._acks.append(reply)
        if not self._ack_scheduled:
            self._ack_scheduled = True
            try:
                self._loop.call_soon_threadsafe(self._send_acks)
            except RuntimeError:  # the loop has closed: it is redelivered later
                pass

    def _send_acks(self) -> None:
        self._ack_scheduled = False
        if self._ack_task is None or self._ack_task.done():
            self._ack_task = asyncio.ensure_future(self._flush_acks())

    async def _flush_acks(self) -> None:
        # One task sends every queued ack: nats-py's publish only appends to its write
        # buffer (and wakes its flusher), so this rarely yields.
        nc = self._nc
        while self._acks and nc is not None:
            await nc.publish(self._acks.popleft(), b"+ACK")


def _no_ack() -> None:
    pass


def _ack_metadata(reply: str) -> tuple[int, float, int, int]:
    """``(times delivered, stream timestamp in seconds, consumer sequence, messages still
    pending)`` from a JetStream ack subject (consumer sequence 0 and pending 1 when unreadable).

    ``$JS.ACK.<stream>.<consumer>.<delivered>.<sseq>.<cseq>.<ns>.<pending>`` or, with a
    domain and account hash, two tokens more after ``$JS.ACK``.
    """
    tokens = reply.split(".")
    offset = 2 if len(tokens) == 9 else 4
    try:
        return (int(tokens[offset + 2]), int(tokens[offset + 5]) / 1e9,
                int(tokens[offset + 4]), int(tokens[offset + 6]))
    except (IndexError, ValueError):
        return 1, time.time(), 0, 1
