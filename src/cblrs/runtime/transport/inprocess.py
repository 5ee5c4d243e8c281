"""The in-process transport: an embedded broker with the MQTT transport's behaviour.

:class:`InProcessBroker` keeps sessions, retained messages and last wills in memory;
:class:`InProcessTransport` is one client of it. Services and tests run on it exactly as on
MQTT (:mod:`cblrs.runtime.transport.mqtt_transport`): both implement
:class:`cblrs.runtime.transport.protocol.Transport`.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

from cblrs.runtime.transport.protocol import (
    ACCEPTED,
    NO_MATCHING_SUBSCRIBERS,
    Handler,
    PublishResult,
    TransportError,
    Will,
    _HandlerTable,
    _Incoming,
    _no_ack,
)
from cblrs.runtime.transport.topics import topic_matches, validate_filter, validate_topic

logger = logging.getLogger(__name__)



@dataclass
class _Stored:
    message_id: int
    topic: str
    payload: bytes
    qos: int
    retain: bool = False
    topic_filter: str | None = None



@dataclass
class _Session:
    client_id: str
    persistent: bool
    subscriptions: dict[str, int] = field(default_factory=dict)
    pending: deque[_Stored] = field(default_factory=deque)
    inflight: OrderedDict[int, _Stored] = field(default_factory=OrderedDict)
    transport: InProcessTransport | None = None
    will: Will | None = None



class InProcessBroker:
    """A thread-safe broker inside the process: the embedded default (no server needed).

    It keeps sessions (subscriptions, un-acknowledged and queued QoS 1 messages) of
    persistent clients across disconnections and retained messages per topic.
    """

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._sessions: dict[str, _Session] = {}
        self._retained: dict[str, bytes] = {}
        self._ids = itertools.count(1)

    def session_count(self) -> int:
        """Number of sessions held (connected or not)."""
        with self._lock:
            return len(self._sessions)

    def queued(self, client_id: str) -> int:
        """Messages waiting for ``client_id`` (queued plus un-acknowledged)."""
        with self._lock:
            session = self._sessions.get(client_id)
            return 0 if session is None else len(session.pending) + len(session.inflight)

    # Called by InProcessTransport ------------------------------------------------------

    def _attach(self, transport: InProcessTransport) -> bool:
        with self._lock:
            session = self._sessions.get(transport.client_id)
            present = session is not None and transport.persistent and session.persistent
            if session is not None and session.transport is not None:
                session.transport._taken_over()  # MQTT session takeover: old client goes away
            if not present:
                session = _Session(transport.client_id, transport.persistent)
                self._sessions[transport.client_id] = session
            assert session is not None
            session.transport = transport
            session.will = transport.will
            for stored in session.inflight.values():
                transport._enqueue(stored, duplicate=True)
            while session.pending:
                stored = session.pending.popleft()
                session.inflight[stored.message_id] = stored
                transport._enqueue(stored, duplicate=False)
            return present

    def _detach(self, transport: InProcessTransport, publish_will: bool) -> None:
        with self._lock:
            session = self._sessions.get(transport.client_id)
            if session is None or session.transport is not transport:
                return
            session.transport = None
            will = session.will
            if not session.persistent:
                del self._sessions[transport.client_id]
            else:
                # Un-acknowledged QoS 1 messages stay in flight, to be redelivered.
                pass
            if publish_will and will is not None:
                self._publish(will.topic, will.payload, will.qos, will.retain)

    def _subscribe(self, transport: InProcessTransport, topic_filter: str, qos: int) -> None:
        with self._lock:
            session = self._sessions[transport.client_id]
            session.subscriptions[topic_filter] = qos
            for topic, payload in self._retained.items():
                if topic_matches(topic_filter, topic):
                    stored = _Stored(
                        next(self._ids), topic, payload, qos, retain=True, topic_filter=topic_filter
                    )
                    if qos > 0:
                        session.inflight[stored.message_id] = stored
                    transport._enqueue(stored, duplicate=False)

    def _publish(self, topic: str, payload: bytes, qos: int, retain: bool) -> bool:
        """Route a message; returns whether any subscription matched."""
        routed = False
        with self._lock:
            if retain:
                if payload:
                    self._retained[topic] = payload
                else:
                    self._retained.pop(topic, None)
            for session in self._sessions.values():
                # One copy per matching subscription, as Mosquitto does.
                for topic_filter, granted_qos in session.subscriptions.items():
                    if not topic_matches(topic_filter, topic):
                        continue
                    routed = True
                    delivered_qos = min(qos, granted_qos)
                    stored = _Stored(
                        next(self._ids), topic, payload, delivered_qos, topic_filter=topic_filter
                    )
                    if session.transport is not None:
                        if delivered_qos > 0:
                            session.inflight[stored.message_id] = stored
                        session.transport._enqueue(stored, duplicate=False)
                    elif delivered_qos > 0 and session.persistent:
                        session.pending.append(stored)
        return routed

    def _ack(self, client_id: str, message_id: int) -> None:
        with self._lock:
            session = self._sessions.get(client_id)
            if session is not None:
                session.inflight.pop(message_id, None)



_STOP = object()



class InProcessTransport:
    """A client of an :class:`InProcessBroker`.

    Args:
        broker: the broker shared by all clients of the process.
        client_id: session id; a persistent session is resumed by a new transport with the
            same id.
        persistent: keep the session (subscriptions, queued QoS 1 messages) after close.
        will: published on close (by the broker when ``unclean``).
    """

    def __init__(
        self,
        broker: InProcessBroker,
        client_id: str,
        *,
        persistent: bool = True,
        will: Will | None = None,
    ):
        self.broker = broker
        self.client_id = client_id
        self.persistent = persistent
        self.will = will
        self._handlers = _HandlerTable()
        self._subscribed: set[str] = set()
        self._qos: dict[str, int] = {}
        self._queue: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._connected = False
        self._connect_hooks: list[Callable[[bool], None]] = []

    @property
    def connected(self) -> bool:
        """Whether the connection to the broker is up now."""
        return self._connected

    def add_connect_hook(self, hook: Callable[[bool], None]) -> None:
        """Call ``hook(session_present)`` after every (re)connection."""
        self._connect_hooks.append(hook)

    def clear_will(self) -> None:
        """The client announced its end itself: publish no will on a clean close."""
        self.will = None
        with self.broker._lock:
            session = self.broker._sessions.get(self.client_id)
            if session is not None and session.transport is self:
                session.will = None

    def connect(self) -> None:
        """Connect (see :class:`~cblrs.runtime.transport.protocol.Transport`)."""
        if self._connected:
            return
        self._thread = threading.Thread(
            target=self._run, name=f"cblrs-inprocess-{self.client_id}", daemon=True
        )
        self._thread.start()
        self._connected = True
        present = self.broker._attach(self)
        if not present:
            self._subscribed.clear()
        for topic_filter in self._handlers.filters():
            if topic_filter not in self._subscribed:
                self.broker._subscribe(self, topic_filter, self._qos[topic_filter])
                self._subscribed.add(topic_filter)
        for hook in self._connect_hooks:
            hook(present)

    def publish(
        self,
        topic: str,
        payload: bytes,
        qos: int = 1,
        retain: bool = False,
        on_result: PublishResult | None = None,
    ) -> None:
        """Publish a message (see :class:`~cblrs.runtime.transport.protocol.Transport`)."""
        validate_topic(topic)
        if qos not in (0, 1):
            raise TransportError(f"QoS must be 0 or 1, got {qos}.")
        if not self._connected:
            raise TransportError(f"{self.client_id}: publish before connect().")
        routed = self.broker._publish(topic, bytes(payload), qos, retain)
        if on_result is not None:
            on_result(ACCEPTED if routed else NO_MATCHING_SUBSCRIBERS)

    def subscribe(self, topic_filter: str, handler: Handler, qos: int = 1) -> None:
        """Subscribe a handler to a topic filter (see
        :class:`~cblrs.runtime.transport.protocol.Transport`)."""
        validate_filter(topic_filter)
        if qos not in (0, 1):
            raise TransportError(f"QoS must be 0 or 1, got {qos}.")
        self._qos[topic_filter] = max(qos, self._qos.get(topic_filter, 0))
        adopted = self._handlers.add(topic_filter, handler)
        for item in adopted:
            self._queue.put(("orphan", item))
        if self._connected and topic_filter not in self._subscribed:
            self.broker._subscribe(self, topic_filter, self._qos[topic_filter])
            self._subscribed.add(topic_filter)

    def resubscribe(self, topic_filter: str) -> None:
        """Subscribe again: the broker sends the filter's retained messages again."""
        if not self._connected:
            raise TransportError(f"{self.client_id}: not connected.")
        self.broker._subscribe(self, topic_filter, self._qos.get(topic_filter, 1))

    def flush(self, timeout: float) -> bool:
        # Publishing hands the message to the broker synchronously: nothing is ever pending.
        """Wait until every publish made so far is answered; False on timeout (see
        :class:`~cblrs.runtime.transport.protocol.Transport`)."""
        return True

    def pending(self) -> int:
        """Publishes not yet answered: always 0, the in-process broker answers at once."""
        return 0

    def close(self, unclean: bool = False, timeout: float = 5.0) -> None:
        """Disconnect, stop its threads (:class:`~cblrs.runtime.transport.protocol.Transport`)."""
        if not self._connected:
            return
        self._connected = False
        self.broker._detach(self, publish_will=True)
        self._queue.put(_STOP)
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    # Called by the broker --------------------------------------------------------------

    def _enqueue(self, stored: _Stored, duplicate: bool) -> None:
        self._queue.put(("message", stored, duplicate))

    def _taken_over(self) -> None:
        self._connected = False
        self._queue.put(_STOP)

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                return
            if item[0] == "orphan":
                self._handlers.dispatch(item[1])
                continue
            _, stored, duplicate = item

            def send_ack(message_id: int = stored.message_id) -> None:
                self.broker._ack(self.client_id, message_id)

            self._handlers.dispatch(
                _Incoming(
                    stored.topic,
                    stored.payload,
                    duplicate,
                    stored.retain,
                    stored.qos,
                    send_ack if stored.qos > 0 else _no_ack,
                    None if stored.topic_filter is None else (stored.topic_filter,),
                )
            )
