"""The dashboard's live feed: a read-only MQTT client of one plane, relayed to browsers.

:class:`LiveFeed` subscribes (as the broker's read-only ``viewer``) to the plane's track
updates, analytics events, the matcher's live summary and the cameras' status, validates
each message with its schema, turns it into the compact JSON the page draws and hands it to
every connected page (:class:`Subscriber`, one per Server-Sent-Events stream). A page that
connects mid-run first gets what the feed holds: the last track frame, the last live
summary, the cameras' status, the recent events and the recent alerts.

Messages to the page (``type``):

* ``tracks`` — ``{"t": capture time, "rows": [[track, x, y, class], ...]}``, one per
  track update, empty ones too (the page drops marks not seen for a moment: stale marks
  disappear); corrections of the past (updates with ``corrected_from``: the matcher
  re-tracked late messages) are counted, not drawn;
* ``event`` — an analytics event (``cblrs.events/1`` fields), once per ``key``;
* ``live`` — the matcher's live summary (counts, occupancy, dwell, camera health);
* ``status`` — ``{"camera", "online"}`` from a camera's status topic;
* ``alert`` — an alert episode fired or cleared (``cblrs.alerts/1`` fields: episode, rule,
  kind, subject, state, timestamp, since, value, threshold, and ``active``: the episodes
  firing then), once per ``(episode, state)``;
* ``hello`` — first message of a stream: the mode and the plane.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any

import msgspec
import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.runtime.outputs.events import decode_alert, decode_event, decode_live
from cblrs.runtime.transport.mqtt_transport import MqttSettings, MqttTransport
from cblrs.runtime.transport.topics import (
    TopicError,
    alerts_topic,
    events_topic,
    live_topic,
    parse_status_topic,
    status_filter,
    tracks_topic,
)
from cblrs.runtime.wire import RejectedMessage, decode_status, decode_tracks

logger = logging.getLogger(__name__)

RECENT_EVENTS = 50
RECENT_ALERTS = 50
"""Events a newly connected page gets."""
QUEUE_LIMIT = 256
"""Messages waiting for a slow page; beyond it the oldest track frames are dropped."""

_encoder = msgspec.json.Encoder()


ToSite = Callable[[Any], Any]
"""Maps (N, 2) pseudo positions to site metres (:meth:`cblrs.privacy.PseudoKey.to_site`)."""


def tracks_frame(update: Any, to_site: ToSite | None = None) -> dict[str, Any]:
    """A decoded track update as the page's ``tracks`` message (positions to the centimetre;
    mapped to the site by ``to_site`` when the matcher works in pseudo coordinates)."""
    tracks = update.tracks
    world_xy = tracks.world_xy if to_site is None else to_site(tracks.world_xy)
    rows = [
        [track, round(x, 2), round(y, 2), CLASS_NAMES[klass] if 0 <= klass < len(CLASS_NAMES)
         else None]
        for track, (x, y), klass in zip(tracks.track_id.tolist(), world_xy.tolist(),
                                        tracks.class_id.tolist(), strict=True)
    ]
    timestamp = update.timestamp
    if timestamp is None and len(tracks):
        timestamp = float(tracks.timestamp.max())
    return {"type": "tracks", "t": timestamp, "rows": rows}


class Subscriber:
    """One page's queue of messages (filled from any thread, read on the event loop)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, limit: int = QUEUE_LIMIT):
        self._loop = loop
        self._items: deque[bytes | dict] = deque()
        self._limit = limit
        self._ready = asyncio.Event()
        self.dropped = 0

    def push(self, item: dict[str, Any]) -> None:
        """Queue ``item`` (thread-safe)."""
        self._loop.call_soon_threadsafe(self._push, item)

    def _push(self, item: dict[str, Any]) -> None:
        self._items.append(item)
        if len(self._items) > self._limit:
            # A page that cannot keep up loses old track frames, never events or counts.
            for index, queued in enumerate(self._items):
                if isinstance(queued, dict) and queued.get("type") == "tracks":
                    del self._items[index]
                    self.dropped += 1
                    break
            else:
                self._items.popleft()
                self.dropped += 1
        self._ready.set()

    async def next(self) -> dict[str, Any]:
        while not self._items:
            self._ready.clear()
            await self._ready.wait()
        item = self._items.popleft()
        assert isinstance(item, dict)
        return item


def sse(item: dict[str, Any]) -> bytes:
    """One Server-Sent-Events message."""
    return b"data: " + _encoder.encode(item) + b"\n\n"


class LiveFeed:
    """The plane's messages, validated and relayed to pages (see the module docstring).

    Args:
        settings: broker address and the viewer's credentials.
        plane_id: the plane shown.
        client_id: the MQTT client id (a clean session: nothing queues while away).
    """

    def __init__(
        self, settings: MqttSettings, plane_id: int, client_id: str,
        to_site: ToSite | None = None,
    ):
        self.plane_id = int(plane_id)
        self.to_site = to_site
        self.settings = settings
        self.transport = MqttTransport(client_id, settings, persistent=False)
        self._lock = threading.Lock()
        self._subscribers: set[Subscriber] = set()
        self._last_tracks: dict[str, Any] | None = None
        self._last_live: dict[str, Any] | None = None
        self._status: dict[str, bool] = {}
        self._events: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self._alerts: OrderedDict[tuple[str, str], dict[str, Any]] = OrderedDict()
        self.counters = {"tracks": 0, "events": 0, "live": 0, "alerts": 0, "rejected": 0,
                         "corrections": 0}
        self.last_message_at: float | None = None

    def start(self) -> None:
        """Connect and subscribe.

        Raises:
            cblrs.runtime.transport.protocol.TransportError: the broker is unreachable, refuses the
                credentials, or refuses a subscription (the ACL).
        """
        self.transport.connect()
        plane = self.plane_id
        for topic, handler in ((tracks_topic(plane), self._on_tracks),
                               (events_topic(plane), self._on_event),
                               (live_topic(plane), self._on_live),
                               (alerts_topic(plane), self._on_alert),
                               (status_filter(plane), self._on_status)):
            self.transport.subscribe(topic, handler,
                                     qos=1 if topic.endswith(("events", "alerts")) else 0)

    def close(self) -> None:
        """Disconnect from the broker."""
        self.transport.close(timeout=1.0)

    @property
    def connected(self) -> bool:
        return self.transport.connected

    # ------------------------------------------------------------------ pages
    def subscribe(self, loop: asyncio.AbstractEventLoop) -> Subscriber:
        """A new page: its queue, primed with what the feed holds."""
        subscriber = Subscriber(loop)
        with self._lock:
            self._subscribers.add(subscriber)
            backlog: list[dict[str, Any]] = [{"type": "hello", "mode": "live",
                                              "plane": self.plane_id}]
            backlog += [{"type": "status", "camera": camera, "online": online}
                        for camera, online in self._status.items()]
            if self._last_live is not None:
                backlog.append(self._last_live)
            backlog += [{**event, "recent": True} for event in self._events.values()]
            backlog += [{**alert, "recent": True} for alert in self._alerts.values()]
            if self._last_tracks is not None:
                backlog.append(self._last_tracks)
        for item in backlog:
            subscriber.push(item)
        return subscriber

    def unsubscribe(self, subscriber: Subscriber) -> None:
        with self._lock:
            self._subscribers.discard(subscriber)

    def _broadcast(self, item: dict[str, Any]) -> None:
        self.last_message_at = time.time()
        with self._lock:
            subscribers = list(self._subscribers)
        for subscriber in subscribers:
            subscriber.push(item)

    # ------------------------------------------------------------------ MQTT handlers
    def _on_tracks(self, delivery: Any) -> None:
        try:
            update = decode_tracks(delivery.payload)
        except RejectedMessage as error:
            self._reject("tracks", error)
            return
        finally:
            delivery.ack()
        if update.corrected_from is not None:  # the past, re-tracked: not where people are
            with self._lock:
                self.counters["corrections"] += 1
            return
        frame = tracks_frame(update, self.to_site)
        with self._lock:
            self._last_tracks = frame
            self.counters["tracks"] += 1
        self._broadcast(frame)

    def _on_event(self, delivery: Any) -> None:
        try:
            event = decode_event(delivery.payload)
        except RejectedMessage as error:
            self._reject("event", error)
            return
        finally:
            delivery.ack()
        item = {"type": "event", **msgspec.to_builtins(event)}
        item.pop("schema", None)
        if self.to_site is not None and item.get("world_xy") is not None:
            item["world_xy"] = self.to_site(np.array([item["world_xy"]]))[0].tolist()
        with self._lock:
            if event.key in self._events:  # QoS 1 may deliver it again
                return
            self._events[event.key] = item
            while len(self._events) > RECENT_EVENTS:
                self._events.popitem(last=False)
            self.counters["events"] += 1
        self._broadcast(item)

    def _on_live(self, delivery: Any) -> None:
        try:
            live = decode_live(delivery.payload)
        except RejectedMessage as error:
            self._reject("live", error)
            return
        finally:
            delivery.ack()
        item = {"type": "live", **msgspec.to_builtins(live)}
        item.pop("schema", None)
        with self._lock:
            self._last_live = item
            self.counters["live"] += 1
        self._broadcast(item)

    def _on_alert(self, delivery: Any) -> None:
        try:
            alert = decode_alert(delivery.payload)
        except RejectedMessage as error:
            self._reject("alert", error)
            return
        finally:
            delivery.ack()
        item = {"type": "alert", **msgspec.to_builtins(alert)}
        item.pop("schema", None)
        key = (alert.episode, alert.state)
        with self._lock:
            if key in self._alerts:  # QoS 1, or the retained one again after a reconnection
                return
            self._alerts[key] = item
            while len(self._alerts) > RECENT_ALERTS:
                self._alerts.popitem(last=False)
            self.counters["alerts"] += 1
        self._broadcast(item)

    def _on_status(self, delivery: Any) -> None:
        try:
            _, camera = parse_status_topic(delivery.topic)
            status = decode_status(delivery.payload)
        except (TopicError, RejectedMessage) as error:
            self._reject("status", error)
            return
        finally:
            delivery.ack()
        online = status.state == "online"
        with self._lock:
            self._status[camera] = online
        self._broadcast({"type": "status", "camera": camera, "online": online})

    def _reject(self, what: str, error: Exception) -> None:
        with self._lock:
            self.counters["rejected"] += 1
        logger.warning("dashboard: ignored a %s message: %s", what, error)
