"""Publish/subscribe transports: an embedded in-process broker and MQTT 5 (paho-mqtt).

Both implement :class:`Transport` with the same behaviour, so services and tests run on either:

* topics with ``+``/``#`` wildcard filters, retained messages, a last will;
* QoS 1 with *manual* acknowledgement: a delivery is acknowledged only when the handler
  calls ``delivery.ack()`` (a service acks after storing durably, which makes the chain
  at-least-once end to end); un-acknowledged messages are delivered again, flagged
  ``duplicate``, when a persistent session reconnects;
* persistent sessions: QoS 1 messages for a disconnected subscriber wait for it;
* publishes made while the broker is away are queued in memory and sent on reconnection,
  in the order they were made (a publish never overtakes an earlier one, also across a
  reconnection);
* every QoS 1 publish can report the broker's answer (``on_result``: the MQTT 5 reason code,
  0 = accepted, 0x10 = no matching subscribers, >= 0x80 = refused).

Handlers run on the transport's own thread (paho's network thread, or one dispatcher thread
per in-process client), one delivery at a time, in arrival order. A handler must not block
for long; it may call ``publish`` and ``ack`` but should not call ``subscribe``.

Example:
    >>> broker = InProcessBroker()  # or: MqttTransport("matcher1", MqttSettings(port=1883))
    >>> matcher = InProcessTransport(broker, "matcher1")
    >>> matcher.connect()
    >>> def store(delivery: Delivery) -> None:
    ...     print(delivery.topic, delivery.payload)
    ...     delivery.ack()  # after storing durably
    >>> matcher.subscribe("cblrs/1/+/detections", store)
    >>> camera = InProcessTransport(broker, "CVLab1")
    >>> camera.connect()
    >>> camera.publish("cblrs/1/CVLab1/detections", b"{}")
    >>> camera.close(); matcher.close()  # doctest: +SKIP

The protocol and the types both transports share live here; the transports themselves in
:mod:`cblrs.runtime.transport.inprocess` and :mod:`cblrs.runtime.transport.mqtt_transport`
(their names can also be imported from this module).
"""

from __future__ import annotations

import importlib
import itertools
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

from cblrs.errors import CblrsError
from cblrs.runtime.transport.topics import topic_matches

logger = logging.getLogger(__name__)



class TransportError(CblrsError):
    """Connecting, subscribing or publishing failed (refused, unreachable, not authorised)."""



@dataclass(frozen=True)
class Delivery:
    """One received message.

    Attributes:
        topic: the topic it was published on.
        payload: the bytes.
        ack: acknowledge it (idempotent); until then the broker may deliver it again.
        duplicate: True when this is a redelivery of a message not acknowledged before.
        retain: True when it comes from the broker's retained store.
        qos: the delivery's QoS (0 or 1).
    """

    topic: str
    payload: bytes
    ack: Callable[[], None]
    duplicate: bool = False
    retain: bool = False
    qos: int = 1



@dataclass(frozen=True)
class Will:
    """Last will: published by the broker when a client disappears without a clean close.

    Transports also publish it themselves on a clean ``close()``, so a retained status topic
    always ends "offline".
    """

    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = True


Handler = Callable[[Delivery], None]
PublishResult = Callable[[int], None]



ACCEPTED = 0x00


ACCEPTED = 0x00
NO_MATCHING_SUBSCRIBERS = 0x10


"""A broker may accept a publish nobody has subscribed to (Mosquitto 2.0 answers 0 then)."""
PACKET_TOO_LARGE = 0x95


"""Larger than the broker's Maximum Packet Size: refused by the transport before sending."""
LOST = -1



def refused(reason: int) -> bool:
    """Whether a publish answer is a refusal (MQTT 5 reason codes >= 0x80, or :data:`LOST`)."""
    return reason >= 0x80 or reason == LOST



@runtime_checkable
class Transport(Protocol):
    """The interface services use; see the module docstring for the guarantees."""

    client_id: str

    def connect(self) -> None:
        """Connect (resuming the persistent session of ``client_id`` if there is one)."""

    def publish(
        self,
        topic: str,
        payload: bytes,
        qos: int = 1,
        retain: bool = False,
        on_result: PublishResult | None = None,
    ) -> None:
        """Publish; queued in memory while disconnected; ``on_result`` gets the broker's
        answer (QoS 1)."""

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        """Call ``handler`` for each message matching ``topic_filter``."""

    def flush(self, timeout: float) -> bool:
        """Wait until every publish so far is acknowledged; False on timeout."""

    def close(self, unclean: bool = False, timeout: float = 5.0) -> None:
        """Flush (up to ``timeout``), publish the will, disconnect.

        With ``unclean=True`` nothing is flushed and the broker publishes the will, as
        after a crash.
        """



def _once(send: Callable[[], None]) -> Callable[[], None]:
    """``send`` made idempotent (a handler may call ``ack`` more than once, from any thread).

    ``next()`` on an ``itertools.count`` is atomic, so exactly one call sends, without
    allocating a lock per delivery.
    """
    calls = itertools.count()

    def ack() -> None:
        if next(calls) == 0:
            send()

    return ack



class _AckCounter:
    """Acknowledge once, after every handler a delivery went to has acknowledged it."""

    def __init__(self, count: int, send: Callable[[], None]):
        self._remaining = count
        self._send = send
        self._lock = threading.Lock()

    def part(self) -> Callable[[], None]:
        done = threading.Event()

        def ack() -> None:
            if done.is_set():
                return
            done.set()
            with self._lock:
                self._remaining -= 1
                fire = self._remaining == 0
            if fire:
                self._send()

        return ack



@dataclass(frozen=True)
class _Incoming:
    """A message as a transport receives it, before it is handed to handlers.

    ``filters`` names the subscriptions it was delivered for (None: any that matches).
    """

    topic: str
    payload: bytes
    duplicate: bool
    retain: bool
    qos: int
    send_ack: Callable[[], None]
    filters: tuple[str, ...] | None = None



_MAX_ROUTES = 4096



class _HandlerTable:
    """Handlers by filter, plus deliveries that arrived before a matching handler existed.

    A broker delivers one copy of a message per matching subscription (Mosquitto does); each
    copy goes to the handlers of its own filter only, so a handler sees a message once.
    """

    def __init__(self) -> None:
        self._handlers: dict[str, list[Handler]] = {}
        self._orphans: list[_Incoming] = []
        self._routes: dict[tuple[str, tuple[str, ...] | None], list[Handler]] = {}
        """Handlers by (topic, filters): a plane has few topics, so routing is a lookup."""
        self._lock = threading.Lock()

    def add(self, topic_filter: str, handler: Handler) -> list[_Incoming]:
        """Register ``handler``; return the waiting deliveries it should now receive."""
        with self._lock:
            self._handlers.setdefault(topic_filter, []).append(handler)
            self._routes.clear()
            adopted = [item for item in self._orphans if self._wants(topic_filter, item)]
            self._orphans = [item for item in self._orphans if item not in adopted]
        return adopted

    @staticmethod
    def _wants(topic_filter: str, item: _Incoming) -> bool:
        if item.filters is not None:
            return topic_filter in item.filters
        return topic_matches(topic_filter, item.topic)

    def filters(self) -> list[str]:
        with self._lock:
            return list(self._handlers)

    def dispatch(self, item: _Incoming) -> None:
        with self._lock:
            key = (item.topic, item.filters)
            handlers = self._routes.get(key)
            if handlers is None:
                handlers = [
                    handler
                    for topic_filter, registered in self._handlers.items()
                    if self._wants(topic_filter, item) and topic_matches(topic_filter, item.topic)
                    for handler in registered
                ]
                if handlers:
                    if len(self._routes) >= _MAX_ROUTES:
                        self._routes.clear()
                    self._routes[key] = handlers
            if not handlers:
                self._orphans.append(item)
                return
        if len(handlers) == 1:
            acks = [_once(item.send_ack)]
        else:
            counter = _AckCounter(len(handlers), item.send_ack)
            acks = [counter.part() for _ in handlers]
        for handler, ack in zip(handlers, acks, strict=True):
            delivery = Delivery(
                item.topic, item.payload, ack, item.duplicate, item.retain, item.qos
            )
            try:
                handler(delivery)
            except Exception:
                logger.exception("handler for %s failed; message left unacknowledged", item.topic)



def reason_text(reason: int) -> str:
    """A readable name for an MQTT reason code (or :data:`LOST`)."""
    if reason == LOST:
        return "not acknowledged before the transport closed"
    try:
        # lazy: only MQTT reason codes need paho here (the in-process transport does not)
        from paho.mqtt.packettypes import PacketTypes
        from paho.mqtt.reasoncodes import ReasonCode

        return str(ReasonCode(PacketTypes.PUBACK, identifier=reason))
    except Exception:
        return f"reason code 0x{reason:02x}"


def _no_ack() -> None:
    pass


# The transports import this module; their names are offered here too (lazily: importing
# them here at module level would make an import cycle).
_MOVED = {
    "InProcessBroker": "cblrs.runtime.transport.inprocess",
    "InProcessTransport": "cblrs.runtime.transport.inprocess",
    "MqttSettings": "cblrs.runtime.transport.mqtt_settings",
    "MqttTransport": "cblrs.runtime.transport.mqtt_transport",
    "unreachable_reason": "cblrs.runtime.transport.mqtt_settings",
}


def __getattr__(name: str) -> Any:
    """``from cblrs.runtime.transport.protocol import MqttTransport`` and co. keep working."""
    if name in _MOVED:

        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
