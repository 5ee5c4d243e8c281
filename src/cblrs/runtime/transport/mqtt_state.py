"""The state of a :class:`~cblrs.runtime.transport.mqtt_transport.MqttTransport`: its counters,
its paho client, and the queues, events and tables its parts share.

The parts are mixins of this class, one module each: the ordered publish queue
(:mod:`~cblrs.runtime.transport.mqtt_publisher`) and the subscriptions with their deliveries
(:mod:`~cblrs.runtime.transport.mqtt_subscriptions`); the connection and the public API are
:class:`~cblrs.runtime.transport.mqtt_transport.MqttTransport` itself.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cblrs.runtime.transport.mqtt_settings import MqttSettings
from cblrs.runtime.transport.protocol import (
    TransportError,
    Will,
    _HandlerTable,
)
from cblrs.runtime.transport.rate_limited import RateLimitedLog

if TYPE_CHECKING:
    from cblrs.runtime.transport.mqtt_publisher import _Outgoing

logger = logging.getLogger("cblrs.runtime.transport.mqtt_transport")
"""The transport's logger: its parts log under the one name (levels set on it, as the
dashboard does, hold for all of them)."""


__all__ = ["_MqttState"]  # in the API reference: the attributes of MqttTransport are set here


class _MqttState:
    """What an MQTT transport holds (its constructor: see
    :class:`~cblrs.runtime.transport.mqtt_transport.MqttTransport`)."""

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

    def _require_client(self):
        if self._client is None:
            raise TransportError(f"{self.client_id}: not connected (call connect() first).")
        return self._client
