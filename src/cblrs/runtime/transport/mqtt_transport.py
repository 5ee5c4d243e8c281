"""The MQTT transport: :class:`MqttTransport` over paho-mqtt (MQTT 5, or 3.1.1 when asked).

It implements :class:`cblrs.runtime.transport.protocol.Transport`: QoS 1 with manual
acknowledgement, persistent sessions, publishes queued while the broker is away and sent in order on
reconnection, and each publish's reason code reported back. It stays one module because
:class:`MqttTransport` is one state machine (connection, ordered outgoing queue, subscriptions,
acknowledgements) driven by paho's callbacks, and its parts only make sense together.
"""

from __future__ import annotations

import errno
import logging
import socket
import ssl
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode
from paho.mqtt.subscribeoptions import SubscribeOptions

from cblrs.runtime.transport.paho_client import BufferedClient, buffered_reads_supported
from cblrs.runtime.transport.protocol import (
    ACCEPTED,
    LOST,
    PACKET_TOO_LARGE,
    Handler,
    PublishResult,
    TransportError,
    Will,
    _HandlerTable,
    _Incoming,
    reason_text,
    refused,
)
from cblrs.runtime.transport.rate_limited import RateLimitedLog
from cblrs.runtime.transport.topics import (
    filters_overlap,
    topic_matches,
    validate_filter,
    validate_topic,
)

_paho_logger = logging.getLogger("cblrs.runtime.transport.mqtt_transport.paho")

logger = logging.getLogger(__name__)

SESSION_TAKEN_OVER = 0x8E
"""MQTT 5 DISCONNECT reason: another connection with the same client id took the session."""
SHORT_CONNECTION_S = 10.0
"""A connection the broker closes this soon after accepting it counts as a take-over:
Mosquitto 2.0.11 closes the older of two clients with one client id without the MQTT 5 reason
0x8E, and two such clients then take the session from each other many times a second."""




@dataclass(frozen=True)
class MqttSettings:
    """How to reach and log into a broker.

    Attributes:
        host: broker address.
        port: broker port (1883 plain, 8883 usual for TLS).
        username: user name (None: anonymous).
        password: password; pass it from the environment or a 0600 file, never the repo.
        ca_file: CA certificate that signed the broker's certificate; enables TLS.
        cert_file: client certificate (PEM), when the broker requires one.
        key_file: the client certificate's private key (PEM).
        keepalive_s: MQTT keepalive, seconds.
        session_expiry_s: how long the broker keeps a disconnected persistent session.
        reconnect_min_s: first reconnection delay; doubles up to ``reconnect_max_s``.
        reconnect_max_s: longest reconnection delay.
        connect_timeout_s: how long ``connect()`` waits for the broker's answer.
        max_inflight: QoS 1 publishes sent but not yet acknowledged, at most (paho's window).
        max_handed: publishes handed to paho and not yet acknowledged, at most; the rest
            wait in the transport's own queue (paho numbers messages with 16 bits and fails
            past 65 535 outstanding ones).
        tcp_nodelay: disable Nagle's algorithm on the connection, so small packets (a
            track update, an acknowledgement) leave at once instead of up to ~40 ms later.
        protocol: MQTT version: "5", "3.1.1" (e.g. the NATS server's MQTT listener, which
            refuses MQTT 5), or "auto" (MQTT 5, and 3.1.1 when the broker refuses version 5).
            Under 3.1.1 the session expiry is the broker's, overlapping subscriptions get no
            identifiers, ``close(unclean=True)`` does not make the broker send the will, and
            a publish's answer is always "accepted" (3.1.1 has no reason codes).
    """

    host: str = "127.0.0.1"
    port: int = 1883
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None
    keepalive_s: int = 30
    session_expiry_s: int = 24 * 3600
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    connect_timeout_s: float = 5.0
    max_inflight: int = 100
    max_handed: int = 1000
    tcp_nodelay: bool = True
    protocol: str = "5"

    @property
    def mqtt5(self) -> bool:
        """Whether MQTT 5 is spoken (else 3.1.1)."""
        return self.protocol != "3.1.1"

    @property
    def tls(self) -> bool:
        """Whether the connection uses TLS."""
        return self.ca_file is not None

    @property
    def address(self) -> str:
        """``host:port`` of the broker, for messages."""
        return f"{self.host}:{self.port}"



@dataclass
class _Outgoing:
    """A publish waiting in the transport's queue or handed to paho."""

    topic: str
    payload: bytes
    qos: int
    retain: bool
    on_result: PublishResult | None



class MqttTransport:
    """A client of an MQTT 5 broker (paho-mqtt >= 2.1), with the :class:`Transport` behaviour.

    Args:
        client_id: MQTT client id; a persistent session is resumed by a new transport with
            the same id.
        settings: broker address, credentials, TLS files, timeouts.
        persistent: ``clean_start=False`` with a session expiry, so the broker keeps QoS 1
            messages for this client while it is away.
        will: last will (e.g. retained "offline" on the client's status topic).

    Publishes wait in an in-memory queue of the transport (unbounded) and are handed to paho
    in order, at most ``settings.max_handed`` at a time, only while connected. After a
    reconnection, paho first sends again what it held unacknowledged, and only once all of
    that is acknowledged does the transport hand over newer publishes: paho alone would send
    a publish made during the reconnection ahead of the older ones it re-sends, which
    reorders a camera's stream. Queued publishes are lost if the process exits first (use
    ``flush``, or the camera's disk spool, :mod:`cblrs.runtime.camera.spool`).
    """

    def __init__(
        self,
        client_id: str,
        settings: MqttSettings | None = None,
        *,
        persistent: bool = True,
        will: Will | None = None,
    ):
        self.client_id = client_id
        self.settings = settings or MqttSettings()
        self.persistent = persistent
        self.will = will
        self.refused_publishes = 0
        """QoS 1 publishes the broker acknowledged with a failure code (e.g. not authorised)."""
        self.last_refusal: tuple[str, str] | None = None
        """``(topic, reason)`` of the latest refused publish."""
        self.connections = 0
        """Successful connections so far (1 after the first, more after reconnections)."""
        self.disconnections = 0
        """Connections lost or closed so far."""
        self.takeovers = 0
        """Times another client logged in with this login and took this one's session (the
        broker closes the older connection: MQTT 5 reason 0x8E, or a connection lost less
        than :data:`SHORT_CONNECTION_S` after it was accepted): a login shared by two
        clients, or a stolen one."""
        self._connected_at = 0.0
        self._takeover_log = RateLimitedLog(logger, interval_s=10.0)
        self._handlers = _HandlerTable()
        self._qos: dict[str, int] = {}
        self._subscribed: set[str] = set()
        self._client: Any = None  # paho.mqtt.client.Client, imported lazily
        self._connected = threading.Event()
        self._disconnected = threading.Event()
        self._answered = threading.Event()
        self._attempt_failed = threading.Event()
        self._refusal: str | None = None
        self._condition = threading.Condition()
        self._backlog: deque[_Outgoing] = deque()
        self._handed: dict[int, _Outgoing] = {}
        self._early: dict[int, int] = {}
        self._hold = False
        """True after a reconnection until paho's re-sends are all acknowledged."""
        self._send_lock = threading.Lock()
        self._pump_wanted = False
        self._will_on_close = True
        self._max_packet: int | None = None
        """The broker's Maximum Packet Size (MQTT 5 CONNACK property), if it announced one."""
        self._connect_hooks: list[Callable[[bool], None]] = []
        self._suback: dict[int, list] = {}
        self._background_subscribes: dict[int, str] = {}
        """Subscriptions sent on (re)connection, by packet id, until the broker answers."""
        self._suspected_takeover: tuple[float, Any] | None = None
        """A connection the broker closed soon after accepting it: ``(lived, reason)``; a
        takeover if the next attempt succeeds at once, a broker going away if it fails."""
        self._filter_ids: dict[int, str] = {}
        self._identified: set[str] = set()
        """Filters overlapping another one: subscribed with a subscription identifier so each
        copy the broker sends (one per matching subscription) reaches its own handlers only.
        Identifiers cost paho ~tens of µs per message to parse, so other filters go without."""

    # Public API ------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """Whether the connection to the broker is up now."""
        return self._connected.is_set()

    def add_connect_hook(self, hook: Callable[[bool], None]) -> None:
        """Call ``hook(session_present)`` after every successful (re)connection.

        Hooks run on paho's network thread; they may publish (the publish is queued behind
        anything paho still re-sends) but must not block.
        """
        self._connect_hooks.append(hook)

    def clear_will(self) -> None:
        """The client announced its end itself (e.g. a timestamped "offline"): do not publish
        the will again on a clean close. After a crash the broker still publishes it."""
        self._will_on_close = False

    def connect(self, wait: bool = True) -> None:
        """Start the network thread and connect.

        Args:
            wait: wait for the broker's answer (up to ``settings.connect_timeout_s``) and raise
                if it refuses, cannot be reached or does not answer; with False, return at
                once and keep trying in the background (publishes are queued meanwhile).

        Raises:
            TransportError: refused (bad credentials, not authorised), unreachable (the
                message names the operating system's reason) or no answer in time.
        """
        if self._client is not None:
            return

        settings = self.settings
        client_class = BufferedClient if buffered_reads_supported() else mqtt.Client
        client = client_class(
            callback_api_version=CallbackAPIVersion.VERSION2,
            client_id=self.client_id,
            protocol=mqtt.MQTTv5 if settings.mqtt5 else mqtt.MQTTv311,
            clean_session=None if settings.mqtt5 else not self.persistent,
        )
        if _paho_logger.isEnabledFor(logging.DEBUG):
            # paho formats a log line for every packet once a log callback is set: debug only.
            client.on_log = self._on_log
        client.manual_ack_set(True)
        client.max_queued_messages_set(0)  # the transport bounds what it hands over
        client.max_inflight_messages_set(settings.max_inflight)
        client.reconnect_delay_set(settings.reconnect_min_s, settings.reconnect_max_s)  # type: ignore[arg-type]
        if settings.username is not None:
            client.username_pw_set(settings.username, settings.password)
        if settings.ca_file is not None:
            client.tls_set(
                ca_certs=str(settings.ca_file),
                certfile=str(settings.cert_file) if settings.cert_file else None,
                keyfile=str(settings.key_file) if settings.key_file else None,
                cert_reqs=ssl.CERT_REQUIRED,
                tls_version=ssl.PROTOCOL_TLS_CLIENT,
            )
        if self.will is not None:
            client.will_set(self.will.topic, self.will.payload, self.will.qos, self.will.retain)
        client.on_connect = self._on_connect
        client.on_connect_fail = self._on_connect_fail
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        client.on_publish = self._on_publish
        client.on_subscribe = self._on_subscribe
        client.on_socket_open = _socket_options if settings.tcp_nodelay else _refuse_self_connection
        properties = None
        if settings.mqtt5:
            properties = Properties(PacketTypes.CONNECT)
            properties.SessionExpiryInterval = settings.session_expiry_s if self.persistent else 0
        self._client = client
        self._attempt_failed.clear()
        client.connect_async(
            settings.host,
            settings.port,
            keepalive=settings.keepalive_s,
            clean_start=not self.persistent if settings.mqtt5 else mqtt.MQTT_CLEAN_START_FIRST_ONLY,
            properties=properties,
        )
        client.loop_start()
        if not wait:
            return
        deadline = time.monotonic() + settings.connect_timeout_s
        while not self._answered.wait(0.05):
            if self._attempt_failed.is_set():
                reason = unreachable_reason(settings.host, settings.port)
                if reason is not None:
                    self._abandon()
                    raise TransportError(
                        f"{self.client_id}: cannot reach the MQTT broker at {settings.address}: "
                        f"{reason}."
                    )
                self._attempt_failed.clear()
            if time.monotonic() >= deadline:
                self._abandon()
                raise TransportError(
                    f"{self.client_id}: no answer from the MQTT broker at {settings.address} "
                    f"within {settings.connect_timeout_s:g} s"
                    + (" (is it a TLS port? check the CA file)" if settings.tls else "")
                    + "."
                )
        if self._refusal is not None:
            refusal = self._refusal
            self._abandon()
            if settings.protocol == "auto" and "protocol version" in refusal.lower():
                logger.info("%s: the broker refuses MQTT 5; using MQTT 3.1.1", self.client_id)
                self.settings = replace(settings, protocol="3.1.1")
                self._answered.clear()
                self.connect(wait)
                return
            raise TransportError(
                f"{self.client_id}: the MQTT broker at {settings.address} "
                f"refused the connection: {refusal}."
            )
        # Filters registered before connect() count from the broker's grant, not from the
        # send: a broker stopped in between must not lose them (they are sent again).
        self._wait_for_subscriptions(max(0.0, deadline - time.monotonic()))

    def publish(
        self,
        topic: str,
        payload: bytes,
        qos: int = 1,
        retain: bool = False,
        on_result: PublishResult | None = None,
    ) -> None:
        """Queue a publish; it is handed to paho in order once connected (see the class).

        Args:
            on_result: called once, on paho's network thread, with the broker's MQTT 5
                reason code (QoS 1), or :data:`LOST` if the transport is closed first.
        """
        validate_topic(topic)
        if qos not in (0, 1):
            raise TransportError(f"QoS must be 0 or 1, got {qos}.")
        if self._client is None:
            raise TransportError(f"{self.client_id}: publish before connect().")
        with self._condition:
            self._backlog.append(_Outgoing(topic, bytes(payload), qos, retain, on_result))
        self._pump(blocking=threading.current_thread() is not self._network_thread())

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        """Register ``handler``; when connected, wait for the broker's grant.

        Raises:
            TransportError: the broker refused the subscription (e.g. not authorised by the ACL).
        """
        validate_filter(topic_filter)
        if qos not in (0, 1):
            raise TransportError(f"QoS must be 0 or 1, got {qos}.")
        self._qos[topic_filter] = max(qos, self._qos.get(topic_filter, 0))
        self._filter_ids[_subscription_id(topic_filter)] = topic_filter
        overlapping = [
            other
            for other in self._handlers.filters()
            if other != topic_filter and filters_overlap(other, topic_filter)
        ]
        newly_identified = [other for other in overlapping if other not in self._identified]
        if overlapping:
            self._identified.add(topic_filter)
            self._identified.update(overlapping)
        adopted = self._handlers.add(topic_filter, handler)
        for item in adopted:
            self._handlers.dispatch(item)
        if self._client is not None and self._connected.is_set():
            # Earlier filters now overlapping get their identifier by subscribing again.
            for other in newly_identified:
                if other in self._subscribed:
                    self._subscribe_and_wait(other, self._qos[other])
            if topic_filter in self._subscribed:
                return
            self._subscribed.add(topic_filter)
            codes = self._subscribe_and_wait(topic_filter, self._qos[topic_filter])
            failures = [code for code in codes if code.is_failure]
            if failures:
                self._subscribed.discard(topic_filter)
                raise TransportError(
                    f"{self.client_id}: the broker refused the subscription to "
                    f"{topic_filter}: {failures[0]}."
                )

    def resubscribe(self, topic_filter: str) -> None:
        """Subscribe to a registered filter again, so the broker sends its retained
        messages again (MQTT 5 retain handling 0); needs a connection.

        Raises:
            TransportError: not connected, or the broker refused.
        """
        if not self._connected.is_set():
            raise TransportError(f"{self.client_id}: not connected.")
        codes = self._subscribe_and_wait(topic_filter, self._qos.get(topic_filter, 1))
        failures = [code for code in codes if code.is_failure]
        if failures:
            raise TransportError(
                f"{self.client_id}: the broker refused the subscription to {topic_filter}: "
                f"{failures[0]}."
            )

    def flush(self, timeout: float) -> bool:
        """Wait until every publish so far is acknowledged by the broker; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._condition:
            while self._backlog or self._handed:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._condition.wait(min(remaining, 0.5))
            return True

    def pending(self) -> int:
        """Publishes not yet acknowledged by the broker (queued or handed to paho)."""
        with self._condition:
            return len(self._backlog) + len(self._handed)

    def close(self, unclean: bool = False, timeout: float = 5.0) -> None:
        """Disconnect, stop its threads (:class:`~cblrs.runtime.transport.protocol.Transport`)."""
        client = self._client
        if client is None:
            return

        was_connected = self._connected.is_set()
        if was_connected:
            # Closing a socket with unread data (a SUBACK on its way) makes TCP send a reset,
            # and the broker may then drop our last PUBACKs: read the answers first.
            self._wait_for_subscriptions(timeout)
        if unclean:
            # MQTT 5 "Disconnect with Will Message": the broker publishes the will, as on a crash.
            self._disconnected.clear()
            client.disconnect(
                reasoncode=ReasonCode(PacketTypes.DISCONNECT, identifier=4)
                if self.settings.mqtt5 else None
            )
        else:
            if self.will is not None and was_connected and self._will_on_close:
                self.publish(self.will.topic, self.will.payload, self.will.qos, self.will.retain)
            if not self.flush(timeout):
                logger.warning(
                    "%s: closing with %d publishes not acknowledged by the broker",
                    self.client_id, self.pending(),
                )
            self._disconnected.clear()
            client.disconnect()
        # loop_stop() ends the network thread at once, dropping packets still queued (PUBACKs
        # of messages just handled, the DISCONNECT itself): wait until they are written.
        if was_connected and not self._disconnected.wait(timeout):
            logger.warning("%s: no clean disconnection within %g s", self.client_id, timeout)
        client.loop_stop()
        self._client = None
        self._connected.clear()
        with self._condition:
            lost = list(self._handed.values()) + list(self._backlog)
            self._handed.clear()
            self._backlog.clear()
            self._condition.notify_all()
        for item in lost:
            _report(item, LOST)

    # Internals -------------------------------------------------------------------------

    def _network_thread(self) -> threading.Thread | None:
        client = self._client
        return None if client is None else getattr(client, "_thread", None)

    def _pump(self, blocking: bool) -> None:
        """Hand queued publishes to paho, in order, while connected and within the window.

        Only one thread hands over at a time (``_send_lock``). paho's network thread never
        waits for that lock: it holds paho's own lock when it calls back, and the handing
        thread needs that one inside ``client.publish``; it asks the holder to go on instead.
        """
        while True:
            if not self._send_lock.acquire(blocking=blocking):
                self._pump_wanted = True
                return
            try:
                self._pump_wanted = False
                self._hand_over()
            finally:
                self._send_lock.release()
            if not self._pump_wanted:
                return
            blocking = False

    def _hand_over(self) -> None:
        client = self._client
        while client is not None:
            with self._condition:
                if not (
                    self._backlog
                    and self._connected.is_set()
                    and not self._hold
                    and len(self._handed) < self.settings.max_handed
                ):
                    return
                item = self._backlog.popleft()
            if self._max_packet is not None and (
                len(item.payload) + len(item.topic.encode()) + 32 > self._max_packet
            ):
                # The broker would close the connection, paho would send it again after
                # reconnecting, and so on: refuse it here, as the broker would.
                logger.warning("%s: a %d-byte publish on %s exceeds the broker's packet limit "
                               "of %d bytes; not sent", self.client_id, len(item.payload),
                               item.topic, self._max_packet)
                self._finished(item, PACKET_TOO_LARGE)
                continue
            info = client.publish(item.topic, item.payload, qos=item.qos, retain=item.retain)
            if info.rc not in (mqtt.MQTT_ERR_SUCCESS, mqtt.MQTT_ERR_NO_CONN):
                # Not expected within the window; keep the order by putting it back.
                with self._condition:
                    self._backlog.appendleft(item)
                logger.warning("%s: paho could not take publish on %s: %s", self.client_id,
                               item.topic, mqtt.error_string(info.rc))
                return
            if item.qos == 0:
                _report(item, ACCEPTED)
                continue
            with self._condition:
                early = self._early.pop(info.mid, None)
                if early is None:
                    self._handed[info.mid] = item
            if early is not None:
                self._finished(item, early)

    def _finished(self, item: _Outgoing, reason: int) -> None:
        if refused(reason):
            self.refused_publishes += 1
            self.last_refusal = (item.topic, reason_text(reason))
        _report(item, reason)

    def _wait_for_subscriptions(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        with self._condition:
            while self._background_subscribes:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return
                self._condition.wait(remaining)

    def _require_client(self):
        if self._client is None:
            raise TransportError(f"{self.client_id}: not connected (call connect() first).")
        return self._client

    def _abandon(self) -> None:
        client = self._client
        if client is not None:
            client.disconnect()
            client.loop_stop()
        self._client = None

    def _subscribe_and_wait(self, topic_filter: str, qos: int) -> list:
        client = self._require_client()
        result, mid = self._send_subscribe(client, topic_filter, qos)
        if mid is None:
            raise TransportError(
                f"{self.client_id}: subscribe to {topic_filter} failed ({result})."
            )
        deadline = time.monotonic() + self.settings.connect_timeout_s
        with self._condition:
            while mid not in self._suback:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TransportError(
                        f"{self.client_id}: no answer to the subscription to {topic_filter}."
                    )
                self._condition.wait(remaining)
            return self._suback.pop(mid)

    def _send_subscribe(self, client, topic_filter: str, qos: int) -> tuple:
        if not self.settings.mqtt5:
            return client.subscribe(topic_filter, qos=qos)

        return client.subscribe(
            topic_filter,
            options=SubscribeOptions(qos=qos),
            properties=self._subscribe_properties(topic_filter),
        )

    def _subscribe_properties(self, topic_filter: str):
        return _identifier_properties(topic_filter) if topic_filter in self._identified else None

    def _on_log(self, client, userdata, level, text) -> None:
        # After a wanted disconnection paho's loop runs once more and reports "Client is not
        # connected" as an error: expected, so debug only.
        if level == mqtt.MQTT_LOG_ERR and not text.startswith("Client is not connected"):
            _paho_logger.warning("%s: %s", self.client_id, text)
        elif _paho_logger.isEnabledFor(logging.DEBUG):
            _paho_logger.debug("%s: %s", self.client_id, text)

    def _on_connect_fail(self, client, userdata) -> None:
        self._attempt_failed.set()
        suspected, self._suspected_takeover = self._suspected_takeover, None
        if suspected is not None:
            # The broker closed the connection and then could not be reached: it went away.
            logger.warning("%s: disconnected from %s: %s; reconnecting", self.client_id,
                           self.settings.address, suspected[1])

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            self._refusal = str(reason_code)
            expected = self.settings.protocol == "auto" and "protocol version" in self._refusal
            logger.log(logging.INFO if expected else logging.WARNING,
                       "%s: connection refused by %s: %s", self.client_id,
                       self.settings.address, reason_code)
            self._answered.set()
            return
        self._refusal = None
        self._connected_at = time.monotonic()
        suspected, self._suspected_takeover = self._suspected_takeover, None
        if suspected is not None:
            self._report_takeover(suspected[0])
        if not flags.session_present:
            self._subscribed.clear()

        with self._condition:
            self._background_subscribes.clear()  # answers to a lost connection never come
        for topic_filter in self._handlers.filters():
            if topic_filter not in self._subscribed:
                # Counted as subscribed only once the broker grants it (_on_subscribe): if
                # the connection drops first, the next connection sends it again.
                _, mid = self._send_subscribe(client, topic_filter, self._qos[topic_filter])
                if mid is not None:
                    with self._condition:
                        self._background_subscribes[mid] = topic_filter
        self.connections += 1
        self._max_packet = getattr(properties, "MaximumPacketSize", None)
        with self._condition:
            # paho sends what it holds unacknowledged again right after this callback; newer
            # publishes wait until all of that is acknowledged, so nothing overtakes it.
            self._hold = bool(self._handed)
        log = logger.info if self.connections == 1 else logger.warning
        log("%s: %s %s (session present: %s)", self.client_id,
            "connected to" if self.connections == 1 else "reconnected to",
            self.settings.address, bool(flags.session_present))
        self._connected.set()
        self._answered.set()
        for hook in self._connect_hooks:
            try:
                hook(bool(flags.session_present))
            except Exception:
                logger.exception("%s: connect hook failed", self.client_id)
        self._pump(blocking=False)

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        was_connected = self._connected.is_set()
        self._connected.clear()
        self._disconnected.set()
        if not was_connected:
            return
        self.disconnections += 1
        with self._condition:
            self._hold = bool(self._handed)
        lived = time.monotonic() - self._connected_at
        if int(getattr(reason_code, "value", 0)) == SESSION_TAKEN_OVER:
            self._report_takeover(lived)
        elif reason_code.is_failure and lived < SHORT_CONNECTION_S:
            # Mosquitto 2.0 closes a taken-over MQTT 5 session without reason 0x8E, exactly
            # as a broker that stops does: the next attempt tells them apart.
            self._suspected_takeover = (lived, reason_code)
        elif reason_code.is_failure:
            logger.warning("%s: disconnected from %s: %s; reconnecting", self.client_id,
                           self.settings.address, reason_code)
        else:
            logger.info("%s: disconnected from %s", self.client_id, self.settings.address)

    def _report_takeover(self, lived: float) -> None:
        self.takeovers += 1
        self._takeover_log.log(
            logging.ERROR, "takeover",
            "%s: another client logged in as %s and took over this session (the broker "
            "closed this connection %.1f s after accepting it; %d times so far): a login "
            "must not be shared (give each client its own) and may have been stolen; "
            "reconnecting", self.client_id, self.settings.username or self.client_id,
            lived, self.takeovers)

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        reason = int(getattr(reason_code, "value", 0))
        if refused(reason):
            logger.debug("%s: broker refused publish %d: %s", self.client_id, mid, reason_code)
        with self._condition:
            item = self._handed.pop(mid, None)
            if item is None:
                self._early[mid] = reason
            if self._hold and not self._handed:
                self._hold = False
            self._condition.notify_all()
        if item is not None:
            self._finished(item, reason)
        self._pump(blocking=False)

    def _on_subscribe(self, client, userdata, mid, reason_codes, properties) -> None:
        failures = [code for code in reason_codes if code.is_failure]
        with self._condition:
            topic_filter = self._background_subscribes.pop(mid, None)
            if topic_filter is None:
                self._suback[mid] = list(reason_codes)
            elif not failures:
                self._subscribed.add(topic_filter)
            self._condition.notify_all()
        if failures:
            logger.warning("%s: subscription %d refused: %s", self.client_id, mid, failures[0])

    def _on_message(self, client, userdata, message) -> None:
        mid, qos = message.mid, message.qos

        def send_ack() -> None:
            if qos > 0 and self._client is client:
                client.ack(mid, qos)

        identifiers = getattr(message.properties, "SubscriptionIdentifier", None)
        filters = None
        if identifiers:
            if isinstance(identifiers, int):
                identifiers = [identifiers]
            known = [self._filter_ids[i] for i in identifiers if i in self._filter_ids]
            filters = tuple(known) if known else None
        elif self._identified:
            # A copy for a subscription without identifier: not for the identified filters.
            filters = tuple(
                topic_filter
                for topic_filter in self._handlers.filters()
                if topic_filter not in self._identified
                and topic_matches(topic_filter, message.topic)
            )
        self._handlers.dispatch(
            _Incoming(
                message.topic,
                message.payload,
                bool(message.dup),
                bool(message.retain),
                qos,
                send_ack,
                filters,
            )
        )



def _report(item: _Outgoing, reason: int) -> None:
    if item.on_result is not None:
        try:
            item.on_result(reason)
        except Exception:
            logger.exception("publish result handler for %s failed", item.topic)



def _refuse_self_connection(client, userdata, sock) -> None:
    """paho's on_socket_open: refuse a TCP connection to itself.

    Reconnecting to a local broker that is down, a client can draw the broker's own port as
    its source port and connect to itself (TCP simultaneous open); it would then hold the
    port the broker needs to start again. The OSError makes paho retry later.
    """
    try:
        same = sock.getsockname() == sock.getpeername()
    except (OSError, AttributeError):
        return
    if same:
        sock.close()
        raise OSError(errno.ECONNREFUSED, "connected to itself: nothing listens on that port")



def _socket_options(client, userdata, sock) -> None:
    """paho's on_socket_open: refuse a self-connection, disable Nagle's algorithm (paho
    does not set TCP_NODELAY)."""
    _refuse_self_connection(client, userdata, sock)
    try:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except (OSError, AttributeError):  # not a TCP socket (e.g. a unix socket): nothing to do
        pass



def unreachable_reason(host: str, port: int, timeout: float = 2.0) -> str | None:
    """Why a TCP connection to ``host:port`` fails (the OS's words), or None if it opens."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except TimeoutError:
        return f"no TCP answer within {timeout:g} s"
    except OSError as error:
        return error.strerror or str(error)



def _subscription_id(topic_filter: str) -> int:
    """A stable MQTT 5 subscription identifier for a filter (1 .. 2**28 - 1).

    Stable across processes, so a resumed persistent session's messages still name the
    filter they were delivered for.
    """
    return zlib.crc32(topic_filter.encode()) % (2**28 - 2) + 1



def _identifier_properties(topic_filter: str):
    properties = Properties(PacketTypes.SUBSCRIBE)
    properties.SubscriptionIdentifier = _subscription_id(topic_filter)
    return properties
