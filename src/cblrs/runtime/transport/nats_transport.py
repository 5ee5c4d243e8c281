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
* **connecting**: :meth:`NatsTransport.connect` waits for a first server as long as it takes;
  ``connect(wait=False)`` (a camera) connects in the background instead, publishes waiting in
  memory meanwhile, and :meth:`NatsTransport.wait_connected` says in one sentence why no server
  answers yet (refused, a silent port, TLS); a refused login ends the attempts
  (``connect_failure``, ``on_failure``);
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

Its parts, one module each, are mixins of :class:`NatsTransport`, which keeps the public API,
the event loop and the connection: the shared state
(:mod:`~cblrs.runtime.transport.nats_state`), stream setup and limits
(:mod:`~cblrs.runtime.transport.nats_streams`), the subscriptions and the durable consumer
(:mod:`~cblrs.runtime.transport.nats_consumer`), the publisher with its acknowledgements and
the connection's liveness probe (:mod:`~cblrs.runtime.transport.nats_publisher`) and the plane
lease (:mod:`~cblrs.runtime.transport.nats_lease`). The subject mapping, stream names and
message ids are in :mod:`~cblrs.runtime.transport.nats_subjects`, the settings and TLS in
:mod:`~cblrs.runtime.transport.nats_settings` (both usable without nats-py).
"""

from __future__ import annotations

import asyncio
import logging
import re
import threading
import time
from collections.abc import Coroutine
from typing import Any
from urllib.parse import urlsplit

from cblrs.runtime.transport.mqtt_settings import unreachable_reason
from cblrs.runtime.transport.nats_consumer import _NatsConsumer
from cblrs.runtime.transport.nats_lease import _NatsLease
from cblrs.runtime.transport.nats_publisher import _NatsPublisher
from cblrs.runtime.transport.nats_settings import (
    LeaseSettings,
    NatsSettings,
    _is_login_refusal,
    _is_tls_failure,
    attempt_reason,
)
from cblrs.runtime.transport.nats_subjects import (
    _classify,
    message_id,
    site_subject,
    stream_of,
)
from cblrs.runtime.transport.protocol import Handler, TransportError
from cblrs.runtime.transport.topics import validate_filter, validate_topic

__all__ = ["LeaseSettings", "NatsSettings", "NatsTransport"]

logger = logging.getLogger(__name__)


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


class NatsTransport(_NatsPublisher, _NatsConsumer, _NatsLease):
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

    backbone_name = "the NATS servers"
    """What the services call this backbone in messages."""

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
        self._start_loop()
        try:
            self._run(self._open(), None)
        except BaseException:
            self._shutdown_loop()
            raise

    def connect(self, wait: bool = True) -> None:
        """:meth:`open` if not yet done, then start the subscriptions and the consumer.

        Args:
            wait: wait for the first connection (as long as it takes: an absent server is
                waited for). False: return at once and connect in the background, retrying
                every ``reconnect_wait_s``; publishes wait in memory and subscriptions are
                made once connected. :meth:`wait_connected` then tells why it is not
                connected yet, and a refused login ends the attempts
                (:attr:`connect_failure`, ``on_failure``).

        Raises:
            TransportError: as :meth:`open`, or the consumer could not be set up.
        """
        if not wait:
            self._connect_in_background()
            return
        self.open()
        if self._started:
            return
        self._started = True
        self._run(self._start(), None)

    def wait_connected(self, timeout: float) -> str | None:
        """After ``connect(wait=False)``: wait up to ``timeout`` seconds for the connection.

        Returns:
            None once connected; else why not, one sentence naming the servers and the
            reason the client saw (refused, no answer, TLS), as soon as every server failed
            once (a refused port at once, a silent one after ``connect_timeout_s``).

        Raises:
            TransportError: the servers refused the login (it will not get better).
        """
        deadline = time.monotonic() + timeout
        while True:
            if self.connect_failure is not None:
                raise TransportError(self.connect_failure)
            if self._connected.is_set():
                return None
            error = self._attempt_error
            if error is not None and self._failed_attempts >= len(self.settings.servers):
                break
            if time.monotonic() >= deadline:
                break
            time.sleep(0.02)
        where = ", ".join(self.settings.servers)
        if error is None:
            return (f"{self.client_id}: no answer from the NATS servers at {where} within "
                    f"{timeout:g} s.")
        reason = attempt_reason(error, self.settings)
        if isinstance(error, TimeoutError):
            # nats-py does not say whether the TCP connection or the greeting timed out.
            addresses = [urlsplit(server) for server in self.settings.servers]
            tcp = [unreachable_reason(url.hostname or "127.0.0.1", url.port or 4222)
                   for url in addresses]
            if all(tcp):
                reason = str(tcp[0])
        return f"{self.client_id}: cannot reach the NATS servers at {where}: {reason}."

    def pending_on(self, topic: str) -> int:
        """Stream publishes on ``topic`` not yet acknowledged by the stream (e.g. a camera's
        detections while the servers are away)."""
        with self._condition:
            return self._pending_by_subject[site_subject(topic, self._site)]

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
            self._pending_by_subject[subject] += 1
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
        elif not self._started:
            self._core[topic_filter] = None
        else:
            self._run(self._add_core(topic_filter), self.settings.connect_timeout_s)

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
        if self._connecting is not None:
            self._connecting.cancel()  # still connecting in the background: stop that
        if self._nc is None:  # never connected: nothing can be taken or said now
            if self.pending():
                logger.warning("%s: closing with %d publishes never sent (no NATS server "
                               "answered)", self.client_id, self.pending())
            self._shutdown_loop()
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

    def _start_loop(self) -> None:
        self._loop = asyncio.new_event_loop()
        self._publish_wake = asyncio.Event()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name=f"cblrs-nats-{self.client_id}", daemon=True
        )
        self._thread.start()

    def _connect_in_background(self) -> None:
        _import_nats()
        if self._thread is not None:
            return
        self.settings.tls_context()  # unreadable TLS files: one sentence now, not later
        self._start_loop()
        self._started = True
        assert self._loop is not None
        self._connecting = asyncio.run_coroutine_threadsafe(self._open_and_start(), self._loop)

    async def _open_and_start(self) -> None:
        """The background connection: :meth:`_open` (retrying until a server answers, unless
        it refuses the login), then the subscriptions and the consumer."""
        try:
            await self._open(background=True)
            await self._start()
        except asyncio.CancelledError:
            raise
        except Exception as error:
            sentence = str(error).rstrip(".") if isinstance(error, TransportError) else (
                f"{self.client_id}: connecting to NATS failed: {error or type(error).__name__}")
            self.connect_failure = sentence + "."
            logger.error("%s", self.connect_failure)
            if self.on_failure is not None:
                self.on_failure(self.connect_failure)

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

    async def _open(self, background: bool = False) -> None:
        """Connect (nats-py retries until a server answers), then the lease, the answers'
        inbox and the publisher. A refused login ends the attempts, and so does a failed TLS
        handshake unless ``background`` (then it is retried, as an absent server is)."""
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
            if not self._connected.is_set():
                self._attempt_error = error
                self._failed_attempts += 1
            if _is_login_refusal(error):
                refusals.append(f"the servers refused the login {settings.username or '(none)'}"
                                " (wrong or missing user name and password)")
            elif _is_tls_failure(error) and not background:
                refusals.append(attempt_reason(error, settings))
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
        if self._publish_wake is None:
            self._publish_wake = asyncio.Event()
        self._ack_prefix = self._nc.new_inbox() + "."
        await self._nc.subscribe(self._ack_prefix + "*", cb=self._on_publish_answer)
        self._publisher = asyncio.get_running_loop().create_task(self._publish_loop())

    async def _start(self) -> None:
        self._core_live = True  # from now on _add_core subscribes at once
        for topic_filter in list(self._core):
            await self._subscribe_core(topic_filter)
        if self._bound:
            await self._start_consumer()

    async def _add_core(self, topic_filter: str) -> None:
        """A plain subscription made after :meth:`connect`: at once once the subscriptions
        are made, else left to :meth:`_start` (on this loop, so it is made once)."""
        self._core[topic_filter] = None
        if self._core_live:
            await self._subscribe_core(topic_filter)

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


_PERMISSION = re.compile(r'permissions violation for (publish|subscription) to "([^"]+)"', re.I)



async def _cancel_tasks() -> None:
    """Cancel every other task of the loop (nats-py's readers, flushers, subscriptions)."""
    tasks = [task for task in asyncio.all_tasks() if task is not asyncio.current_task()]
    for task in tasks:
        task.cancel()
    if tasks:  # bounded: a task that swallowed its cancellation must not hold the close
        await asyncio.wait(tasks, timeout=2.0)
