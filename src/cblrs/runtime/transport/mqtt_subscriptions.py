"""The subscriptions of an MQTT transport and their deliveries (:class:`_MqttSubscriptions`,
a part of :class:`~cblrs.runtime.transport.mqtt_transport.MqttTransport`).

Subscribing waits for the broker's answer (a refused filter is one sentence); filters that
overlap another get a stable subscription identifier so that each copy the broker sends
reaches its own handlers only; deliveries go to the handlers with a manual acknowledgement.
"""

from __future__ import annotations

import logging
import time
import zlib

from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.subscribeoptions import SubscribeOptions

from cblrs.runtime.transport.mqtt_state import _MqttState
from cblrs.runtime.transport.protocol import (
    TransportError,
    _Incoming,
)
from cblrs.runtime.transport.topics import (
    topic_matches,
)

logger = logging.getLogger("cblrs.runtime.transport.mqtt_transport")
"""The transport's logger: its parts log under the one name (levels set on it, as the
dashboard does, hold for all of them)."""


class _MqttSubscriptions(_MqttState):
    """Subscribing, the broker's answers, and deliveries to the handlers."""

    def _wait_for_subscriptions(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        with self._condition:
            while self._background_subscribes:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return
                self._condition.wait(remaining)

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
