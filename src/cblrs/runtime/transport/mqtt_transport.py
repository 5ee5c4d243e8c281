"""The MQTT transport: :class:`MqttTransport` over paho-mqtt (MQTT 5, or 3.1.1 when asked).

It implements :class:`cblrs.runtime.transport.protocol.Transport`: QoS 1 with manual
acknowledgement, persistent sessions, publishes queued while the broker is away and sent in order on
reconnection, and each publish's reason code reported back.

:class:`MqttTransport` keeps the public API and the connection (paho's connect and disconnect
callbacks); its parts, one module each, are mixins: the shared state
(:mod:`~cblrs.runtime.transport.mqtt_state`), the ordered publish queue
(:mod:`~cblrs.runtime.transport.mqtt_publisher`) and the subscriptions with their deliveries
(:mod:`~cblrs.runtime.transport.mqtt_subscriptions`); the settings and socket options are in
:mod:`~cblrs.runtime.transport.mqtt_settings`.
"""

from __future__ import annotations

import logging
import ssl
import threading
import time
from collections.abc import Callable
from dataclasses import replace

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode

from cblrs.runtime.transport.mqtt_publisher import _MqttPublisher, _Outgoing, _report
from cblrs.runtime.transport.mqtt_settings import (
    MqttSettings,
    _refuse_self_connection,
    _socket_options,
    unreachable_reason,
)
from cblrs.runtime.transport.mqtt_subscriptions import _MqttSubscriptions, _subscription_id
from cblrs.runtime.transport.paho_client import BufferedClient, buffered_reads_supported
from cblrs.runtime.transport.protocol import (
    LOST,
    Handler,
    PublishResult,
    TransportError,
)
from cblrs.runtime.transport.topics import (
    filters_overlap,
    validate_filter,
    validate_topic,
)

__all__ = [
    "SESSION_TAKEN_OVER",
    "SHORT_CONNECTION_S",
    "MqttSettings",
    "MqttTransport",
    "unreachable_reason",
]

_paho_logger = logging.getLogger("cblrs.runtime.transport.mqtt_transport.paho")

logger = logging.getLogger(__name__)

SESSION_TAKEN_OVER = 0x8E
"""MQTT 5 DISCONNECT reason: another connection with the same client id took the session."""
SHORT_CONNECTION_S = 10.0
"""A connection the broker closes this soon after accepting it counts as a take-over:
Mosquitto 2.0.11 closes the older of two clients with one client id without the MQTT 5 reason
0x8E, and two such clients then take the session from each other many times a second."""


class MqttTransport(_MqttPublisher, _MqttSubscriptions):
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

    backbone_name = "the MQTT broker"
    """What the services call this backbone in messages."""

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

    def _abandon(self) -> None:
        client = self._client
        if client is not None:
            client.disconnect()
            client.loop_stop()
        self._client = None

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


