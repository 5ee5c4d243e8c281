"""The state of a :class:`~cblrs.runtime.transport.nats_transport.NatsTransport`: its settings,
its counters, and the queues, tasks and flags its parts share on its one event loop.

The parts are mixins of this class, one module each: the streams
(:mod:`~cblrs.runtime.transport.nats_streams`), the consumer side
(:mod:`~cblrs.runtime.transport.nats_consumer`), the publisher with its acknowledgements
(:mod:`~cblrs.runtime.transport.nats_publisher`) and the plane lease
(:mod:`~cblrs.runtime.transport.nats_lease`); the connection and the public API are
:class:`~cblrs.runtime.transport.nats_transport.NatsTransport` itself.
"""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from cblrs.runtime.transport.nats_settings import LeaseSettings, NatsSettings
from cblrs.runtime.transport.protocol import Will, _HandlerTable, _Incoming

if TYPE_CHECKING:
    from cblrs.runtime.transport.nats_publisher import _Outgoing


__all__ = ["_NatsState"]  # in the API reference: the attributes of NatsTransport are set here


class _NatsState:
    """What a NATS transport holds (its constructor: see
    :class:`~cblrs.runtime.transport.nats_transport.NatsTransport`)."""

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
        self.connect_failure: str | None = None
        """Why a connection made in the background (``connect(wait=False)``) gave up, one
        sentence (the servers refused the login); None while it connects or once connected."""
        self._failed_attempts = 0  # first connection: attempts that failed so far
        self._attempt_error: BaseException | None = None  # ... and the last one's error
        self._connecting: Any = None  # the background connection (a concurrent Future)
        self._core_live = False  # plain subscriptions are made as they come (see _add_core)
        self._pending_by_subject: Counter[str] = Counter()  # under _condition
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
