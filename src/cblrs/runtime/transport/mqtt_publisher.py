"""The ordered publish queue of an MQTT transport (:class:`_MqttPublisher`, a part of
:class:`~cblrs.runtime.transport.mqtt_transport.MqttTransport`).

Publishes wait in the transport's queue and are handed to paho in order, at most
``settings.max_handed`` at a time, only while connected; after a reconnection nothing newer is
handed over until paho's own re-sends are acknowledged. Each publish's reason code goes back
to its ``on_result``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import paho.mqtt.client as mqtt

from cblrs.runtime.transport.mqtt_state import _MqttState
from cblrs.runtime.transport.protocol import (
    ACCEPTED,
    PACKET_TOO_LARGE,
    PublishResult,
    reason_text,
    refused,
)

logger = logging.getLogger("cblrs.runtime.transport.mqtt_transport")
"""The transport's logger: its parts log under the one name (levels set on it, as the
dashboard does, hold for all of them)."""


class _MqttPublisher(_MqttState):
    """Handing queued publishes to paho in order, and their results."""

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


@dataclass
class _Outgoing:
    """A publish waiting in the transport's queue or handed to paho."""

    topic: str
    payload: bytes
    qos: int
    retain: bool
    on_result: PublishResult | None


def _report(item: _Outgoing, reason: int) -> None:
    if item.on_result is not None:
        try:
            item.on_result(reason)
        except Exception:
            logger.exception("publish result handler for %s failed", item.topic)
