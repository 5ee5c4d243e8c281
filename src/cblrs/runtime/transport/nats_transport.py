"""NATS JetStream transport (nats-py): the clustered, replicated backbone beside MQTT.

:class:`NatsTransport` implements :class:`~cblrs.runtime.transport.protocol.Transport` with the same
behaviour the services rely on, on a NATS server or cluster with JetStream:

* **topics** stay MQTT topics for the services; on the wire they are NATS subjects, mapped
  exactly as the NATS server's MQTT listener maps them (``/`` -> ``.``, ``.`` -> ``//``,
  ``+`` -> ``*``, ``#`` -> ``>``), so a camera publishing MQTT 3.1.1 to that listener on
  ``cblrs/<plane>/<camera>/detections`` lands on ``cblrs.<plane>.<camera>.detections``.
  With a site id (``NatsSettings.site``) every subject starts ``cblrs.<site>.``, so several
  sites share one cluster;
* **streams**, two per plane (replicated over up to three nodes), each with its own leader:
  ``CBLRS_P<plane>`` (``CBLRS_<site>_P<plane>``) keeps the plane's detections and camera
  status for ``retention_s``; ``CBLRS_P<plane>_TRACKS`` its track updates, analytics
  events and alerts (a stream made before alerts had theirs gets the subject added when the
  admin's client next looks it up). A client that manages streams
  (``NatsSettings.manage``: an admin, or a server without users) creates them when first
  needed; a deployment made before per-plane streams keeps its one ``CBLRS`` stream (see
  :meth:`NatsTransport._resolve_stream`);
* **security**: a login's permissions (:mod:`cblrs.runtime.broker.nats_auth`) are enforced by
  the servers; answers come to the login's own inbox prefix; a refused login, TLS handshake,
  publish or subscription is one sentence (``refused_publishes``, ``refused_subjects``);
* **durable consumer** (``durable=``): the subscriptions that fall in the plane's detections
  stream (``consume="tracks"``: its tracks stream, the linker's way to read a plane's track
  updates) are served by one durable pull consumer with explicit acknowledgements (a runtime
  login only reads it and resets it to replay): ``delivery.ack()`` acknowledges
  (the matcher does so after its SQLite commit, as on MQTT), un-acknowledged messages come
  again after ``ack_wait_s`` or to the next holder, flagged ``duplicate``; a status message
  older than the connection is flagged ``retain`` (history, like an MQTT retained message);
  other subscriptions are plain NATS subscriptions;
* **publishes** to a stream are JetStream publishes, each with a ``Nats-Msg-Id``
  (``<plane>.<camera>.<sequence>`` for detections, ``<plane>.<timestamp>`` for a track
  update), sent again with the same id until the stream acknowledges them, so a retry after a
  leader change or a lost connection is stored once (a camera's own re-send of an
  unconfirmed message carries a suffix, ``publish(..., resend=)``, so that it reaches the
  matcher, which confirms it); ``flush`` waits for those acknowledgements. They are
  pipelined: up to ``publish_window`` leave in order on the one connection before their
  acknowledgements come back; after a failure nothing more is sent until the window settles,
  then what was not acknowledged goes again in its order (a publish stored after a later one,
  possible only when a leader dies between two of them, is counted in ``reordered``).
  Publishes made while the servers are away wait in memory;
* **plane lease** (``lease=``): a key (``plane-<plane>``, ``<site>.plane-<plane>``) with a
  time to live in the replicated key-value bucket ``cblrs_leases``; :meth:`connect` refuses
  (one sentence) when another client holds it, the transport renews it every third of its
  TTL and deletes it on a clean close. Losing it (another holder took it) stops deliveries
  and calls ``on_failure``.

NATS has no last will: the will is published on a clean ``close()`` only.

The nats-py client is asyncio: its event loop runs in a thread of the transport and handlers
run on that thread, one delivery at a time, as on paho's network thread.

Example:
    >>> settings = NatsSettings.from_url("nats://127.0.0.1:4222")       # doctest: +SKIP
    >>> matcher = NatsTransport("matcher1", settings, durable="cblrs-plane-1")  # doctest: +SKIP
    >>> matcher.subscribe("cblrs/1/+/detections", store_then_ack)          # doctest: +SKIP
    >>> matcher.connect()                                                 # doctest: +SKIP

It stays one module because :class:`NatsTransport` (about 900 lines) is one asyncio state
machine — connection, JetStream streams and consumers, the ordered publishing window,
acknowledgements, leases — whose parts share its event loop and state. The subject mapping,
stream names and message ids are in :mod:`~cblrs.runtime.transport.nats_subjects`, the
settings in :mod:`~cblrs.runtime.transport.nats_settings` (both usable without nats-py).
"""

from __future__ import annotations

import asyncio
import bisect
import functools
import json
import logging
import os
import re
import socket
import ssl
import threading
import time
from collections import deque
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, replace
from typing import Any

from cblrs.runtime.transport.nats_settings import LeaseSettings, NatsSettings
from cblrs.runtime.transport.nats_subjects import (
    LEASE_BUCKET,
    LEGACY_DETECTIONS_STREAM,
    LEGACY_TRACKS_STREAM,
    _classify,
    detections_stream,
    message_id,
    site_subject,
    site_topic,
    stream_of,
    stream_subjects,
    subject_root,
    tracks_stream,
)
from cblrs.runtime.transport.protocol import Handler, TransportError, Will, _HandlerTable, _Incoming
from cblrs.runtime.transport.topics import topic_matches, validate_filter, validate_topic

logger = logging.getLogger(__name__)

LEASE_UNANSWERED_S = 30.0
"""How long a lease is asked for again while JetStream does not answer (seconds)."""
_NO_PEERS_YET = 10005
"""JetStream's "no suitable peers for placement": what a replicated bucket gets while its
cluster is still forming (not every peer known to the meta leader yet); asked again like an
unanswered request."""
_GIVE_UP_S = 120.0
"""How long the consumer's restart or state may stay unanswerable before the transport goes
on without it (a cluster still recovering answers within that; a refusal never does)."""


_SUBJECT_FULL = 10077
"""JetStream's error code for a publish refused by ``max_msgs_per_subject`` with
``discard_new_per_subject`` (nats-server 2.15.1 answers ``code`` 503 with it)."""


def _import_nats() -> Any:
    try:
        # optional extra: pip install cblrs[nats]
        import nats
    except ImportError:
        raise TransportError(
            "the NATS backbone needs nats-py: pip install cblrs[nats]"
        ) from None
    return nats


# --------------------------------------------------------------------------- transport


_CLOSE = object()


class NatsTransport:
    """A client of a NATS JetStream server or cluster, with the :class:`Transport` behaviour.

    Args:
        client_id: the connection name (and the lease holder's name).
        settings: servers, credentials, stream and consumer settings.
        durable: name of the durable consumer that serves the subscriptions falling in a
            plane's detections stream (one per plane: ``cblrs-plane-<plane>``); None:
            subscriptions are plain NATS subscriptions (live only).
        consume: the stream the durable consumer reads: "detections" (a matcher) or
            "tracks" (a plane's track updates, events and alerts: a linker).
        replay: on connect, rebuild the durable consumer so that it delivers the stream's
            messages from the first one again (a matcher rebuilding an empty store).
        lease: hold this lease while connected (see :class:`LeaseSettings`).
        will: published on a clean close (NATS has no last will).
        on_failure: called (with a sentence) when the lease is lost.
        persistent: accepted for interface compatibility; a durable consumer is persistent.
    """

    def __init__(
        self,
        client_id: str,
        settings: NatsSettings | None = None,
        *,
        durable: str | None = None,
        replay: bool = False,
        lease: LeaseSettings | None = None,
        will: Will | None = None,
        on_failure: Callable[[str], None] | None = None,
        persistent: bool = True,
        consume: str = "detections",
    ):
        if consume not in ("detections", "tracks"):
            raise ValueError(f"consume must be 'detections' or 'tracks', got {consume!r}.")
        self.client_id = client_id
        self.consume = consume
        self.settings = settings or NatsSettings()
        self.durable = durable
        self.replay = replay
        self.lease = lease
        self.will = will
        self.on_failure = on_failure
        self.persistent = persistent
        self.refused_publishes = 0
        """Stream publishes refused for good (a stream limit, a subject this login may not
        publish on); retried ones don't count."""
        self.moved_messages = 0
        """Messages that reached a subscription or a consumer under a subject not its own:
        JetStream delivered them onto a subject another login named as a pull's reply (see
        docs/security.md, "Reply subjects"); dropped (a consumer's: ended), never handed out."""
        self.reordered = 0
        """Publishes stored after a later one of this client: sent again after a failure
        (e.g. a stream leader lost) while a later one in the window was stored."""
        self.refused_subscriptions: list[str] = []
        """Subjects the servers refused this login (permissions; in lower case), latest
        last."""
        self.lease_lost = False
        self._lease_paused = False
        self._held: list[_Incoming] = []
        self._handlers = _HandlerTable()
        self._bound: list[str] = []  # filters served by the durable consumer
        self._core: dict[str, Any] = {}  # filter -> NATS subscription (None until connected)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._nc: Any = None
        self._js: Any = None
        self._connected = threading.Event()
        self._closing = False
        self._started = False
        self._connected_at = time.time()
        self._condition = threading.Condition()
        self._pending = 0
        self._outgoing: deque[_Outgoing] = deque()
        self._resend: list[_Outgoing] = []  # failed publishes, by order, sent first
        self._in_flight: dict[str, _Outgoing] = {}  # reply token -> publish
        self._abandoned: dict[str, _Outgoing] = {}  # tokens given up on (timeout), by token
        self._publish_wake: asyncio.Event | None = None
        self._publisher: asyncio.Task | None = None
        self._ack_prefix = ""
        self._next_order = 0
        self._stored_order = -1
        self._retry_at = 0.0
        self._retry_delay = 0.05
        self._probe: asyncio.Task | None = None  # see _probe_connection
        self.silent_reconnects = 0
        """Reconnections forced because a connection said to be up answered no ping."""
        self._streams: dict[str, str] = {}  # a plane's stream name -> the stream used
        self._stream_locks: dict[str, asyncio.Lock] = {}
        self._consumer_stream = ""
        self._warned_no_stream: set[str] = set()
        self.subject_full_refusals = 0
        """Stream publishes refused because their subject held the stream's maximum of
        messages per subject (sent again later; see :meth:`_subject_full`)."""
        self._full_subjects: set[str] = set()
        self.refused_subjects: deque[str] = deque(maxlen=64)
        """Subjects the servers refused a publish (or request) of this login on, in lower
        case, latest last."""
        self._site = self.settings.site
        self._acks: deque[str] = deque()
        self._ack_scheduled = False
        self._ack_task: asyncio.Future | None = None
        self._core_publishes: set[asyncio.Future] = set()
        self._pull_task: asyncio.Task | None = None
        self._pull_wake: asyncio.Event | None = None
        self._consumer_config: Any = None
        self._resume_at: int | None = None  # restart the consumer here (see _redeliver...)
        self._floor: int | None = None  # where it was last restarted from
        self._redeliver = False  # after a reconnection: before the next pull request
        self._last_delivery = 0  # the consumer's sequence of the last delivery
        self._caught_up = False  # the consumer had nothing more to deliver at last look
        self._check_failing_since: float | None = None
        self._outstanding = 0
        self._last_activity = 0.0
        self._lease_task: asyncio.Task | None = None
        self._lease_revision = 0
        self._lease_value = b""  # what this client writes into its lease key
        self._lease_kv: Any = None
        self.lease_holder = f"{client_id}@{socket.gethostname()}:{os.getpid()}"

    # Public API ------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the connection to the broker is up now."""
        return self._connected.is_set()

    @property
    def caught_up(self) -> bool:
        """Whether the plane's durable consumer has delivered everything its stream holds
        (at the last delivery or check): while not, a camera's silence may only mean its
        messages are still on their way. Without a durable consumer: :attr:`connected`."""
        if self._pull_task is None:
            return self.connected
        return self.connected and self._caught_up and not self._redeliver

    def open(self) -> None:
        """Connect, create the streams if missing and take the lease; deliver nothing yet.

        A service calls this before it starts (so a second matcher of a plane is refused
        before it touches anything), subscribes, then calls :meth:`connect`.

        Raises:
            TransportError: no server answered, a stream could not be created, or the lease
                is held by another client.
        """
        _import_nats()
        if self._thread is not None:
            return
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name=f"cblrs-nats-{self.client_id}", daemon=True
        )
        self._thread.start()
        try:
            self._run(self._open(), None)
        except BaseException:
            self._shutdown_loop()
            raise

    def connect(self, wait: bool = True) -> None:
        """:meth:`open` if not yet done, then start the subscriptions and the consumer.

        Args:
            wait: accepted for interface compatibility; the first connection is always
                waited for (nats-py does not retry a first connection in the background).

        Raises:
            TransportError: as :meth:`open`, or the consumer could not be set up.
        """
        self.open()
        if self._started:
            return
        self._started = True
        self._run(self._start(), None)

    def publish(self, topic: str, payload: bytes, qos: int = 1, retain: bool = False,
                *, resend: str | None = None) -> None:
        """Publish a message (see :class:`~cblrs.runtime.transport.protocol.Transport`).

        Args:
            resend: this is the sender's own re-send of a message it published before (a
                camera that got no confirmation), distinguished by this token: its
                ``Nats-Msg-Id`` gets ``.<resend>`` so that the stream stores it again rather
                than dropping it as the duplicate of the first publish — the matcher, which
                may have stored the first one without ever confirming it, must see it to
                confirm it. (The transport's own retries of one publish keep one id.)
        """
        validate_topic(topic)
        if qos not in (0, 1):
            raise TransportError(f"QoS must be 0 or 1, got {qos}.")
        loop = self._require_loop()
        subject = site_subject(topic, self._site)
        data = bytes(payload)
        if qos == 0 or stream_of(subject, self._site) is None:
            loop.call_soon_threadsafe(self._publish_core, subject, data)
            return
        identifier = message_id(subject, data)
        if identifier is not None and resend is not None:
            identifier = f"{identifier}.{resend}"
        with self._condition:
            self._pending += 1
        loop.call_soon_threadsafe(self._enqueue_publish, subject, data, identifier)

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        """Subscribe a handler to a topic filter (see
        :class:`~cblrs.runtime.transport.protocol.Transport`)."""
        validate_filter(topic_filter)
        if qos not in (0, 1):
            raise TransportError(f"QoS must be 0 or 1, got {qos}.")
        new = topic_filter not in self._bound and topic_filter not in self._core
        self._handlers.add(topic_filter, handler)
        if not new:
            return
        subject = site_subject(topic_filter, self._site)
        kind = _classify(subject, self._site)
        if self.durable is not None and kind is not None and kind[0] == self.consume:
            if self._started:
                # Widening a consumer's filter later would skip what it had passed already.
                raise TransportError(
                    f"{self.client_id}: subscribe to {topic_filter} before connect()."
                )
            self._bound.append(topic_filter)
        else:
            self._core[topic_filter] = None
            if self._started:
                self._run(self._subscribe_core(topic_filter), self.settings.connect_timeout_s)

    def flush(self, timeout: float) -> bool:
        """Wait until every publish made so far is answered; False on timeout (see
        :class:`~cblrs.runtime.transport.protocol.Transport`)."""
        deadline = time.monotonic() + timeout
        with self._condition:
            while self._pending:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._condition.wait(remaining)
            return True

    def pending(self) -> int:
        """Stream publishes not yet acknowledged by the stream."""
        with self._condition:
            return self._pending

    def close(self, unclean: bool = False, timeout: float = 5.0) -> None:
        """Disconnect, stop its threads (:class:`~cblrs.runtime.transport.protocol.Transport`)."""
        if self._loop is None:
            return
        if not unclean:
            if self.will is not None and self._nc is not None:
                self.publish(self.will.topic, self.will.payload, self.will.qos, self.will.retain)
            if not self.flush(timeout):
                logger.warning("%s: closing with %d publishes not acknowledged",
                               self.client_id, self.pending())
        try:
            self._run(self._close(release=not unclean), timeout + 5)
        except Exception as error:  # closing must not fail the caller
            logger.warning("%s: unclean NATS close: %s", self.client_id, error)
        self._shutdown_loop()

    def call(self, coroutine: Coroutine[Any, Any, Any], timeout: float | None = 30.0) -> Any:
        """Run a coroutine on the transport's event loop (with its connection) and wait."""
        return self._run(coroutine, timeout)

    @property
    def jetstream(self) -> Any:
        """The nats-py JetStream context (use it through :meth:`call`)."""
        return self._js

    # Internals: loop ---------------------------------------------------------------------

    def _require_loop(self) -> asyncio.AbstractEventLoop:
        if self._loop is None:
            raise TransportError(f"{self.client_id}: publish before connect().")
        return self._loop

    def _run(self, coroutine: Coroutine[Any, Any, Any], timeout: float | None) -> Any:
        loop = self._require_loop()
        future = asyncio.run_coroutine_threadsafe(coroutine, loop)
        try:
            return future.result(timeout)
        except TimeoutError:
            future.cancel()
            raise TransportError(f"{self.client_id}: no answer from NATS in time.") from None

    def _shutdown_loop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is None:
            return
        if thread is not None and thread is not threading.current_thread():
            try:
                asyncio.run_coroutine_threadsafe(_cancel_tasks(), loop).result(5)
            except Exception:  # stopping anyway
                pass
            loop.call_soon_threadsafe(loop.stop)
            thread.join(5)
            loop.close()
        self._loop = None
        self._thread = None
        self._connected.clear()

    # Internals: connection -----------------------------------------------------------------

    async def _open(self) -> None:
        nats = _import_nats()
        settings = self.settings

        async def on_error(error: Exception) -> None:
            text = str(error)
            denied = _PERMISSION.search(text)
            if denied is not None:
                self._permission_denied(denied[1].lower(), denied[2])
            else:
                logger.debug("%s: NATS: %s", self.client_id, error)

        async def on_disconnected() -> None:
            self._connected.clear()
            self._caught_up = False
            logger.info("%s: disconnected from NATS", self.client_id)

        async def on_reconnected() -> None:
            self._connected.set()
            self._outstanding = 0  # pull requests die with the connection: ask again
            self._redeliver = self._pull_task is not None  # deliveries may have died too
            if self._pull_wake is not None:
                self._pull_wake.set()
            logger.info("%s: reconnected to %s", self.client_id,
                        self._nc.connected_url.netloc if self._nc else "?")

        tls = settings.tls_context()
        refusals: list[str] = []

        async def on_first_error(error: Exception) -> None:
            # nats-py keeps retrying a first connection; a refused login or TLS handshake
            # will not get better, so it ends the attempt (an absent server is waited for).
            text = str(error) or type(error).__name__
            lowered = text.lower()
            if "authorization" in lowered:
                refusals.append(f"the servers refused the login {settings.username or '(none)'}"
                                " (wrong or missing user name and password)")
            elif isinstance(error, ssl.SSLError) or "tls" in lowered or "ssl" in lowered \
                    or "certificate" in lowered:
                refusals.append(f"TLS failed ({text}); the servers require TLS with a client "
                                "certificate signed by their CA (--ca-file, --cert-file, "
                                "--key-file)")
            await on_error(error)

        connecting = asyncio.ensure_future(nats.connect(
            servers=list(settings.servers),
            name=self.client_id,
            user=settings.username,
            password=settings.password,
            tls=tls,
            inbox_prefix=settings.inbox_prefix,
            connect_timeout=max(1, round(settings.connect_timeout_s)),
            reconnect_time_wait=settings.reconnect_wait_s,
            max_reconnect_attempts=-1,
            allow_reconnect=True,
            error_cb=on_first_error,
            disconnected_cb=on_disconnected,
            reconnected_cb=on_reconnected,
            pending_size=64 * 1024 * 1024,
        ))
        while not connecting.done() and not refusals:
            await asyncio.wait({connecting}, timeout=0.05)
        if refusals and not connecting.done():
            connecting.cancel()
            await asyncio.gather(connecting, return_exceptions=True)
        error = None if not connecting.done() or connecting.cancelled() \
            else connecting.exception()
        if refusals or error is not None:
            reason = refusals[0] if refusals else (str(error) or type(error).__name__)
            raise TransportError(
                f"{self.client_id}: cannot connect to NATS at {', '.join(settings.servers)}: "
                f"{reason}."
            )
        self._nc = connecting.result()
        self._nc._error_cb = on_error
        self._js = self._nc.jetstream(timeout=settings.publish_timeout_s * 2)
        self._connected_at = time.time()
        self._connected.set()
        try:
            if self.lease is not None:
                await self._acquire_lease()
        except BaseException as error:
            await self._nc.close()
            self._nc = None
            if isinstance(error, TransportError):
                raise
            raise TransportError(
                f"{self.client_id}: NATS JetStream did not answer ({error or type(error).__name__}"
                "); is JetStream enabled and does the cluster have a leader?"
            ) from None
        self._publish_wake = asyncio.Event()
        self._ack_prefix = self._nc.new_inbox() + "."
        await self._nc.subscribe(self._ack_prefix + "*", cb=self._on_publish_answer)
        self._publisher = asyncio.get_running_loop().create_task(self._publish_loop())

    async def _start(self) -> None:
        for topic_filter in list(self._core):
            await self._subscribe_core(topic_filter)
        if self._bound:
            await self._start_consumer()

    async def _close(self, release: bool) -> None:
        self._closing = True
        tasks = [task for task in (self._pull_task, self._lease_task, self._publisher) if task]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if not self.lease_lost:
            await self._flush_acks()
        nc = self._nc
        if nc is None:
            return
        if release and self.lease is not None and self._lease_kv is not None \
                and not self.lease_lost:
            await self._release_lease()
        try:
            await nc.flush(timeout=2)
        except Exception:
            pass
        await nc.close()
        self._connected.clear()

    async def _release_lease(self) -> None:
        """Delete the lease key so that the next matcher takes the plane at once.

        A renewal cancelled by the close may have been stored without its new revision
        reaching this client: the delete's expected revision is then stale and refused. The
        key is read again and deleted at its revision if it still holds this client's record
        (else the plane would stay held for the lease's TTL: a restarted matcher without
        --lease-wait was refused, and its cameras never confirmed; CI failed once so)."""
        kv, key = self._lease_kv, self.lease.key  # type: ignore[union-attr]
        try:
            await kv.delete(key, last=self._lease_revision)
            return
        except Exception as error:
            logger.debug("lease release at revision %d failed: %s", self._lease_revision, error)
        try:
            entry = await kv.get(key)
            if entry.value == self._lease_value:
                await kv.delete(key, last=entry.revision)
        except Exception as error:  # it expires anyway
            logger.debug("lease release failed: %s", error)

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

    def _permission_denied(self, operation: str, subject: str) -> None:
        """The servers refused ``operation`` ("publish" or "subscription") on ``subject``.

        nats-py hands the servers' error over in lower case, so subjects are compared in
        lower case (camera ids that differ only in case would be confused here).
        """
        if operation.startswith("sub"):
            self.refused_subscriptions.append(subject)
            logger.error("%s: the NATS servers refused the subscription to %s (permissions "
                         "of the login %s)", self.client_id, subject, self.settings.username)
            return
        self.refused_subjects.append(subject)
        reason = f"the login {self.settings.username} may not publish on {subject}"
        waiting = [*self._in_flight.values(), *self._abandoned.values(), *self._resend]
        refused = [item for item in waiting if item.subject.lower() == subject and not item.done]
        for item in refused:
            self._finish(item, refused=reason)
        if not refused:
            logger.error("%s: the NATS servers refused a publish on %s (permissions of the "
                         "login %s)", self.client_id, subject, self.settings.username)

    # Internals: streams ------------------------------------------------------------------

    async def _replicas(self) -> int:
        if self.settings.replicas is not None:
            return self.settings.replicas
        info = self._nc._server_info or {}
        return 3 if info.get("cluster") else 1

    async def _resolve_stream(self, kind: str, plane_id: int) -> str:
        """The stream that stores a plane's ``kind`` ("detections" or "tracks").

        Its own stream (created if missing when this client manages streams); but a
        deployment made by cblrs before per-plane streams has one ``CBLRS`` stream (and
        ``CBLRS_TRACKS``) for every plane, which keeps serving it (with a warning once):
        the server refuses a new stream whose subjects overlap an existing one's.
        """
        maker = detections_stream if kind == "detections" else tracks_stream
        name = maker(plane_id, self._site)
        if name in self._streams:
            return self._streams[name]
        lock = self._stream_locks.setdefault(name, asyncio.Lock())
        async with lock:
            if name not in self._streams:
                self._streams[name] = await self._find_or_create(name, kind, plane_id)
        return self._streams[name]

    async def _find_or_create(self, name: str, kind: str, plane_id: int) -> str:
        # optional extra: pip install cblrs[nats]
        from nats.js.api import RetentionPolicy, StorageType, StreamConfig
        from nats.js.errors import BadRequestError, NotFoundError

        if not self.settings.manages:
            return name  # runtime logins may not look streams up; the admin made them
        try:
            info = await self._js.stream_info(name)
            await self._add_subjects(info, stream_subjects(name, plane_id, self._site), kind)
            return name
        except NotFoundError:
            pass
        except Exception as error:
            raise self._refused_management(f"read the stream {name}", error) from None
        if self._site is None:
            legacy = LEGACY_DETECTIONS_STREAM if kind == "detections" else LEGACY_TRACKS_STREAM
            try:
                info = await self._js.stream_info(legacy)
                if kind == "tracks":
                    await self._add_subjects(info, [f"{subject_root(None)}.*.alerts"], kind)
                logger.warning(
                    "%s: the NATS stream %s made by an older cblrs holds every plane's %s; "
                    "using it (to give each plane its own stream %s, see docs/security.md, "
                    "'Per-plane streams')", self.client_id, legacy, kind, name)
                return legacy
            except NotFoundError:
                pass
        config = StreamConfig(
            name=name, subjects=stream_subjects(name, plane_id, self._site),
            retention=RetentionPolicy.LIMITS, storage=StorageType.FILE,
            max_age=self.settings.retention_s, duplicate_window=self.settings.duplicate_window_s,
            num_replicas=await self._replicas(), allow_direct=True,
        )
        if kind == "detections":
            config = replace(config, **self._camera_limits())
        try:
            await self._js.add_stream(config)
            logger.info("%s: created the NATS stream %s", self.client_id, name)
        except BadRequestError as error:
            if "already in use" not in str(error) and "already exists" not in str(error):
                raise TransportError(f"cannot create the NATS stream {name}: {error}.") from None
        except Exception as error:
            raise self._refused_management(f"create the stream {name}", error) from None
        return name

    def _camera_limits(self) -> dict[str, Any]:
        """A detections stream's limits per camera subject: at most
        ``messages_per_camera`` messages of at most ``max_msg_bytes`` each, and a publish
        beyond is refused (discard new, per subject) rather than dropping anyone's stored
        messages, so a camera that floods fills its own subject, never another camera's."""
        from nats.js.api import DiscardPolicy

        return {"max_msgs_per_subject": self.settings.messages_per_camera,
                "discard": DiscardPolicy.NEW, "discard_new_per_subject": True,
                "max_msg_size": self.settings.max_msg_bytes}

    async def _add_subjects(self, info: Any, subjects: list[str], kind: str) -> None:
        """Give an existing stream the subjects it lacks (one made before alerts were
        stored lacks ``<root>.<plane>.alerts``) and, a plane's detections stream, the
        per-camera limits (one made before them has none)."""
        current = list(info.config.subjects or [])
        missing = [subject for subject in subjects if subject not in current]
        changes: dict[str, Any] = {}
        if missing:
            changes["subjects"] = current + missing
        if kind == "detections":
            limits = self._camera_limits()
            if any(getattr(info.config, key) != value for key, value in limits.items()):
                changes.update(limits)
        if not changes:
            return
        await self._js.update_stream(replace(info.config, **changes))
        logger.info("%s: the NATS stream %s now %s", self.client_id, info.config.name,
                    "; ".join(f"{key} {value}" for key, value in changes.items()))

    def _refused_management(self, what: str, error: Exception) -> TransportError:
        """One sentence for a management call that failed (refused, or no answer)."""
        if self.refused_subjects:
            return TransportError(
                f"{self.client_id}: cannot {what}: the login {self.settings.username} may not "
                f"use {self.refused_subjects[-1]}; only the backbone's admin may (cblrs matcher "
                "--prepare with the admin's login)."
            )
        return TransportError(f"{self.client_id}: cannot {what}: "
                              f"{str(error) or type(error).__name__}.")

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

    def _denial_or(self, error: Exception) -> str:
        """Why a request failed: the permission the servers refused, if they did."""
        if self.refused_subjects:
            return f"the login {self.settings.username} may not use {self.refused_subjects[-1]}"
        return str(error) or type(error).__name__

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

    # Internals: pulling ------------------------------------------------------------------

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

    # Internals: publishing ---------------------------------------------------------------

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
            self._condition.notify_all()
        if self._publish_wake is not None:
            self._publish_wake.set()

    # Internals: lease --------------------------------------------------------------------

    async def _acquire_lease(self) -> None:
        # optional extra: pip install cblrs[nats]
        from nats.errors import NoRespondersError
        from nats.errors import TimeoutError as NatsTimeoutError
        from nats.js.api import KeyValueConfig
        from nats.js.errors import (
            APIError,
            BucketNotFoundError,
            KeyNotFoundError,
            KeyWrongLastSequenceError,
            NoStreamResponseError,
            ServiceUnavailableError,
        )

        lease = self.lease
        assert lease is not None
        # JetStream may not answer for a moment (a cluster that has just started and not yet
        # elected its meta leader, or electing the bucket's leader): asked again for this
        # long, then the error is the answer. Opening the bucket waits too: a matcher started
        # with its cluster failed there at once ("nats: timeout", 1 run in 15 at load 10).
        unanswered = (NoStreamResponseError, NoRespondersError, NatsTimeoutError,
                      ServiceUnavailableError)
        waited_s = max(lease.wait_s, LEASE_UNANSWERED_S)
        unanswered_until = time.monotonic() + waited_s
        said = False

        async def not_yet(error: Exception, what: str, managing: bool = False) -> None:
            """Wait a moment to ask again, or raise: refused (``managing``: a call only the
            backbone's admin may make), or unanswered for too long."""
            nonlocal said
            if self.refused_subjects:  # not unanswered: refused (the servers said so)
                if managing:
                    raise self._refused_management(what, error) from None
                raise TransportError(f"cannot {what}: {self._denial_or(error)}.") from None
            if time.monotonic() >= unanswered_until:
                raise TransportError(
                    f"cannot {what}: JetStream did not answer for {waited_s:g} s "
                    f"({error or type(error).__name__})."
                ) from None
            if not said:
                said = True
                logger.warning("%s: JetStream does not answer yet (%s); asking again for "
                               "the lease %s", self.client_id, error or type(error).__name__,
                               lease.key)
            await asyncio.sleep(0.5)

        while True:
            try:
                kv = await self._js.key_value(LEASE_BUCKET)
                break
            except BucketNotFoundError:
                if not self.settings.manages:
                    raise TransportError(
                        f"the NATS lease bucket {LEASE_BUCKET} does not exist; the backbone's "
                        "admin creates it (cblrs matcher --prepare with the admin's login)."
                    ) from None
                try:
                    kv = await self._js.create_key_value(KeyValueConfig(
                        bucket=LEASE_BUCKET, history=1, ttl=lease.ttl_s, direct=True,
                        replicas=await self._replicas()))
                    break
                except unanswered as error:
                    await not_yet(error, f"create the lease bucket {LEASE_BUCKET}", True)
                except APIError as error:
                    if error.err_code != _NO_PEERS_YET:
                        raise self._refused_management(
                            f"create the lease bucket {LEASE_BUCKET}", error) from None
                    await not_yet(error, f"create the lease bucket {LEASE_BUCKET}", True)
                except Exception as error:
                    raise self._refused_management(f"create the lease bucket {LEASE_BUCKET}",
                                                   error) from None
            except unanswered as error:
                await not_yet(error, f"open the NATS lease bucket {LEASE_BUCKET}")
            except Exception as error:
                raise TransportError(
                    f"cannot open the NATS lease bucket {LEASE_BUCKET}: "
                    f"{self._denial_or(error)}."
                ) from None
        self._lease_kv = kv
        value = json.dumps({"holder": self.lease_holder, "since": time.time()}).encode()
        self._lease_value = value
        deadline = time.monotonic() + lease.wait_s
        while True:
            try:
                self._lease_revision = await kv.create(lease.key, value)
                break
            except unanswered as error:
                await not_yet(error, f"take the lease {lease.key} of "
                                     f"{lease.what or 'the plane'}")
            except KeyNotFoundError:
                # nats-py's create() looks the key up after finding it taken; the holder's
                # lease expired in between: ask again at once.
                await asyncio.sleep(0.05)
                continue
            except KeyWrongLastSequenceError:
                forged = await self._forged_lease(kv)
                if forged is not None:
                    self._lease_revision = await kv.update(lease.key, value, last=forged)
                    break
                holder, age = await self._lease_holder(kv)
                if time.monotonic() >= deadline:
                    raise TransportError(
                        f"{lease.what or lease.key} is already served by {holder} (lease renewed "
                        f"{age:.0f} s ago); stop that matcher first, or give --lease-wait longer "
                        f"than the lease's {lease.ttl_s:g} s time to live to take over once it "
                        "has died"
                    ) from None
                await asyncio.sleep(min(0.5, max(0.05, deadline - time.monotonic())))
            except Exception as error:
                raise TransportError(
                    f"cannot take the lease {lease.key} of {lease.what or 'the plane'}: "
                    f"{self._denial_or(error)}."
                ) from None
        logger.info("%s: holds %s", self.client_id, lease.key)
        self._lease_task = asyncio.get_running_loop().create_task(self._renew_lease(value))

    async def _forged_lease(self, kv: Any) -> int | None:
        """The revision of the lease key if what it holds is no lease record, else None.

        nats-server checks a publish's subject against the login's permissions, never its
        reply subject: any login that may publish into a stream can name the lease key as the
        reply, and JetStream writes its acknowledgement (``{"stream": ..., "seq": ...}``) there.
        Such a write claims nothing; the holder (or a newcomer) writes over it.
        """
        try:
            entry = await kv.get(self.lease.key)  # type: ignore[union-attr]
        except Exception:  # no entry (expired or deleted): nothing forged
            return None
        try:
            record = json.loads(entry.value or b"")
        except ValueError:
            record = None
        if isinstance(record, dict) and isinstance(record.get("holder"), str):
            return None
        logger.warning("%s: %s held a write that is no lease record (%.80r), such as a "
                       "forged reply; writing over it", self.client_id,
                       self.lease.key, entry.value)
        return entry.revision

    async def _lease_holder(self, kv: Any) -> tuple[str, float]:
        try:
            entry = await kv.get(self.lease.key)  # type: ignore[union-attr]
            holder = json.loads(entry.value or b"{}").get("holder", "another matcher")
            created = entry.created
            age = time.time() - created.timestamp() if created is not None else 0.0
            return holder, age
        except Exception:
            return "another matcher", 0.0

    async def _renew_lease(self, value: bytes) -> None:
        # optional extra: pip install cblrs[nats]
        from nats.js.errors import KeyWrongLastSequenceError

        lease = self.lease
        assert lease is not None
        last_renewal = time.monotonic()
        while not self._closing:
            await asyncio.sleep(lease.ttl_s / 3)
            try:
                try:
                    self._lease_revision = await self._lease_kv.update(
                        lease.key, value, last=self._lease_revision)
                except KeyWrongLastSequenceError:
                    # Our entry expired while the cluster was out of reach: take it again
                    # only if nobody has written the key since (expected last revision 0).
                    self._lease_revision = await self._lease_kv.update(lease.key, value, last=0)
                    logger.warning("%s: %s had expired while out of reach; taken again",
                                   self.client_id, lease.key)
                last_renewal = time.monotonic()
                self._resume_deliveries()
            except KeyWrongLastSequenceError:
                forged = await self._forged_lease(self._lease_kv)
                if forged is None:
                    self._lose_lease(
                        f"{lease.what or lease.key} was taken over by another matcher")
                    return
                try:
                    self._lease_revision = await self._lease_kv.update(
                        lease.key, value, last=forged)
                except KeyWrongLastSequenceError:
                    continue  # written again meanwhile: looked at again at the next renewal
                last_renewal = time.monotonic()
                self._resume_deliveries()
            except asyncio.CancelledError:
                raise
            except Exception as error:
                if time.monotonic() - last_renewal > lease.ttl_s and not self._lease_paused:
                    # Another matcher could hold the plane now: hold deliveries until the
                    # lease is ours again (or lost).
                    self._lease_paused = True
                    logger.warning("%s: lease not renewed for %.0f s (%s); holding deliveries",
                                   self.client_id, lease.ttl_s, error or type(error).__name__)

    def _resume_deliveries(self) -> None:
        if not self._lease_paused:
            return
        self._lease_paused = False
        held, self._held = self._held, []
        logger.info("%s: lease renewed; delivering %d held messages", self.client_id, len(held))
        for item in held:
            self._handlers.dispatch(item)

    def _lose_lease(self, reason: str) -> None:
        self.lease_lost = True
        self._acks.clear()
        self._held.clear()
        logger.error("%s: lost the lease: %s; no more deliveries", self.client_id, reason)
        if self.on_failure is not None:
            self.on_failure(f"lost the plane lease: {reason}.")


def _no_ack() -> None:
    pass


_PERMISSION = re.compile(r'permissions violation for (publish|subscription) to "([^"]+)"', re.I)


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


async def _cancel_tasks() -> None:
    """Cancel every other task of the loop (nats-py's readers, flushers, subscriptions)."""
    tasks = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


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
