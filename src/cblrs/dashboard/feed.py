"""The dashboard's live feed: a read-only client of the backbone, relayed to browsers.

:class:`LiveFeed` subscribes (as the backbone's read-only ``viewer``, on MQTT or NATS: any
:class:`~cblrs.runtime.transport.protocol.Transport`) to the track updates, analytics events, live
summaries, alerts and camera and matcher status of one plane or of every plane of a site
(and then also to the linker's global tracks and site summary, plane 0), validates each
message with its schema, turns it into the compact JSON the page draws and hands it to every
connected page (:class:`Subscriber`, one per Server-Sent-Events stream). A page follows one
plane, or the whole site (the overview: every plane's messages, each with its ``plane``).
A page that connects mid-run first gets what the feed holds: per plane, the last track
frame, the last live summary, the cameras' and matchers' status, the recent events and the
recent alerts.

Messages to the page (``type``; each carries ``plane``, 0 for the site's):

* ``tracks`` — ``{"t": capture time, "rows": [[track, x, y, class], ...], "global":
  [global id or null, ...]}``, one per track update, empty ones too (the page drops marks
  not seen for a moment: stale marks disappear); ``global`` (when a linker publishes the
  site's global tracks) names each row's global id, from the linker's newest rows with that
  ``(source_plane, source_track)``; corrections of the past (updates with
  ``corrected_from``: the matcher re-tracked late messages) are counted, not drawn;
* ``event`` — an analytics event (``cblrs.events/1`` fields), once per ``key``;
* ``live`` — the matcher's live summary (counts, occupancy, dwell, camera health); plane 0:
  the linker's (counts on the global tracks);
* ``matcher`` — ``{"matcher", "online"}`` from a matcher's (plane 0: a linker's) status;
* ``status`` — ``{"camera", "online"}`` from a camera's status topic;
* ``alert`` — an alert episode fired or cleared (``cblrs.alerts/1`` fields: episode, rule,
  kind, subject, state, timestamp, since, value, threshold, and ``active``: the episodes
  firing then), once per ``(episode, state)``;
* ``hello`` — first message of a stream: the mode, the plane (None: the overview) and the
  planes of the feed.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.runtime.outputs.events import decode_alert, decode_event, decode_live
from cblrs.runtime.transport.mqtt_transport import MqttTransport
from cblrs.runtime.transport.topics import (
    SITE_PLANE,
    TopicError,
    alerts_topic,
    events_topic,
    linker_status_filter,
    live_topic,
    matcher_status_filter,
    parse_status_topic,
    site_tracks_topic,
    status_filter,
    tracks_topic,
)
from cblrs.runtime.wire import RejectedMessage, decode_status, decode_tracks

logger = logging.getLogger(__name__)

RECENT_EVENTS = 50
RECENT_ALERTS = 50
"""Events a newly connected page gets."""
GLOBAL_IDS = 20_000
"""``(plane, track) -> global id`` pairs held (the newest); older tracks have ended."""
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



def viewer_transport(settings: Any, client_id: str) -> Any:
    """The viewer's transport: NATS for
    :class:`~cblrs.runtime.transport.nats_transport.NatsSettings`, else MQTT (a clean session:
    nothing queues while away)."""
    # lazy: the NATS transport's module is only needed for a NATS backbone
    from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport

    if isinstance(settings, NatsSettings):
        return NatsTransport(client_id, settings)
    return MqttTransport(client_id, settings, persistent=False)


@dataclass
class PlaneState:
    """What the feed holds of one plane (plane 0: the site's, from the linker)."""

    plane_id: int
    last_tracks: dict[str, Any] | None = None
    last_live: dict[str, Any] | None = None
    status: dict[str, bool] = field(default_factory=dict)
    matchers: dict[str, bool] = field(default_factory=dict)
    events: OrderedDict[str, dict[str, Any]] = field(default_factory=OrderedDict)
    alerts: OrderedDict[tuple[str, str], dict[str, Any]] = field(default_factory=OrderedDict)

    def backlog(self) -> list[dict[str, Any]]:
        """What a page that connects now gets first, oldest kind first."""
        plane = self.plane_id
        items: list[dict[str, Any]] = [
            {"type": "status", "plane": plane, "camera": camera, "online": online}
            for camera, online in self.status.items()]
        items += [{"type": "matcher", "plane": plane, "matcher": name, "online": online}
                  for name, online in self.matchers.items()]
        if self.last_live is not None:
            items.append(self.last_live)
        items += [{**event, "recent": True} for event in self.events.values()]
        items += [{**alert, "recent": True} for alert in self.alerts.values()]
        if self.last_tracks is not None:
            items.append(self.last_tracks)
        return items


class LiveFeed:
    """One plane's or a site's messages, validated and relayed to pages (see the module
    docstring).

    Args:
        settings: the backbone's address and the viewer's login:
            :class:`~cblrs.runtime.transport.mqtt_transport.MqttSettings` or
            :class:`~cblrs.runtime.transport.nats_transport.NatsSettings`.
        planes: the plane shown, or the planes of the site (every one is followed).
        client_id: the client id (MQTT: a clean session; nothing queues while away).
        to_site: maps pseudo positions to the site (a matcher on a pseudo site), or None.
        linker: also follow the linker (plane 0: global tracks, the site's counts); the
            default: when more than one plane is followed.
        transport: the transport to use (default: made from ``settings``).
    """

    def __init__(
        self, settings: Any, planes: int | Sequence[int], client_id: str,
        to_site: ToSite | None = None, linker: bool | None = None, transport: Any = None,
    ):
        self.planes = [int(planes)] if isinstance(planes, int) else [int(p) for p in planes]
        if not self.planes:
            raise ValueError("a live feed follows at least one plane")
        self.plane_id = self.planes[0]
        self.linker = len(self.planes) > 1 if linker is None else linker
        self.to_site = to_site
        self.settings = settings
        self.transport = transport if transport is not None else viewer_transport(
            settings, client_id)
        self._lock = threading.Lock()
        self._subscribers: dict[Subscriber, int | None] = {}
        self._state = {plane: PlaneState(plane) for plane in self.planes}
        if self.linker:
            self._state[SITE_PLANE] = PlaneState(SITE_PLANE)
        self._global: OrderedDict[tuple[int, int], int] = OrderedDict()
        self.counters = {"tracks": 0, "events": 0, "live": 0, "alerts": 0, "rejected": 0,
                         "corrections": 0, "global": 0}
        self.last_message_at: float | None = None

    def start(self) -> None:
        """Connect and subscribe.

        Raises:
            cblrs.runtime.transport.protocol.TransportError: the backbone is unreachable,
                refuses the login, or refuses a subscription (the ACL, the NATS permissions).
        """
        self.transport.connect()
        for plane in self.planes:
            self._follow(plane, tracks_topic(plane), self._on_tracks, 0)
            self._follow(plane, events_topic(plane), self._on_event, 1)
            self._follow(plane, live_topic(plane), self._on_live, 0)
            self._follow(plane, alerts_topic(plane), self._on_alert, 1)
            self._follow(plane, status_filter(plane), self._on_status, 0)
            self._follow(plane, matcher_status_filter(plane), self._on_matcher, 0)
        if self.linker:
            self._follow(SITE_PLANE, site_tracks_topic(), self._on_global, 0)
            self._follow(SITE_PLANE, events_topic(SITE_PLANE), self._on_event, 1)
            self._follow(SITE_PLANE, live_topic(SITE_PLANE), self._on_live, 0)
            self._follow(SITE_PLANE, linker_status_filter(), self._on_matcher, 0)

    def _follow(self, plane: int, topic: str, handler: Callable[[int, Any], None],
                qos: int) -> None:
        self.transport.subscribe(topic, lambda delivery: handler(plane, delivery), qos=qos)

    def close(self) -> None:
        """Disconnect from the backbone."""
        self.transport.close(timeout=1.0)

    @property
    def connected(self) -> bool:
        return bool(self.transport.connected)

    def follows(self, plane: int | None) -> bool:
        """Whether a page may follow ``plane`` (None: the overview of every plane)."""
        return plane is None or plane in self.planes

    # ------------------------------------------------------------------ pages
    def subscribe(self, loop: asyncio.AbstractEventLoop, plane: int | None = -1) -> Subscriber:
        """A new page following ``plane`` (None: every plane and the site; the default: the
        feed's first plane): its queue, primed with what the feed holds."""
        shown = self.plane_id if plane == -1 else plane
        subscriber = Subscriber(loop)
        with self._lock:
            self._subscribers[subscriber] = shown
            backlog: list[dict[str, Any]] = [{"type": "hello", "mode": "live", "plane": shown,
                                              "planes": self.planes}]
            for state in self._state.values():
                if shown is None or state.plane_id == shown:
                    backlog += state.backlog()
        for item in backlog:
            subscriber.push(item)
        return subscriber

    def unsubscribe(self, subscriber: Subscriber) -> None:
        with self._lock:
            self._subscribers.pop(subscriber, None)

    def _broadcast(self, item: dict[str, Any]) -> None:
        self.last_message_at = time.time()
        plane = item["plane"]
        with self._lock:
            subscribers = [subscriber for subscriber, shown in self._subscribers.items()
                           if shown is None or shown == plane]
        for subscriber in subscribers:
            subscriber.push(item)

    def global_ids(self, plane: int, tracks: Sequence[int]) -> list[int | None]:
        """The global id of each of ``plane``'s ``tracks`` (None: not linked yet)."""
        with self._lock:
            return [self._global.get((plane, track)) for track in tracks]

    # ------------------------------------------------------------------ handlers
    def _on_tracks(self, plane: int, delivery: Any) -> None:
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
        frame = {**tracks_frame(update, self.to_site), "plane": plane}
        if self.linker:
            frame["global"] = self.global_ids(plane, [row[0] for row in frame["rows"]])
        with self._lock:
            self._state[plane].last_tracks = frame
            self.counters["tracks"] += 1
        self._broadcast(frame)

    def _on_global(self, plane: int, delivery: Any) -> None:
        """The linker's global rows: which global id each plane's track has now."""
        try:
            update = decode_tracks(delivery.payload)
        except RejectedMessage as error:
            self._reject("global tracks", error)
            return
        finally:
            delivery.ack()
        if update.source_plane is None or update.source_track is None:
            return
        pairs = zip(update.source_plane.tolist(), update.source_track.tolist(),
                    update.tracks.track_id.tolist(), strict=True)
        with self._lock:
            for source_plane, source_track, global_id in pairs:
                key = (source_plane, source_track)
                self._global[key] = global_id
                self._global.move_to_end(key)
            while len(self._global) > GLOBAL_IDS:
                self._global.popitem(last=False)
            self.counters["global"] += 1

    def _on_event(self, plane: int, delivery: Any) -> None:
        try:
            event = decode_event(delivery.payload)
        except RejectedMessage as error:
            self._reject("event", error)
            return
        finally:
            delivery.ack()
        item = {"type": "event", **msgspec.to_builtins(event), "plane": plane}
        item.pop("schema", None)
        if self.to_site is not None and item.get("world_xy") is not None:
            item["world_xy"] = self.to_site(np.array([item["world_xy"]]))[0].tolist()
        with self._lock:
            events = self._state[plane].events
            if event.key in events:  # QoS 1 may deliver it again
                return
            events[event.key] = item
            while len(events) > RECENT_EVENTS:
                events.popitem(last=False)
            self.counters["events"] += 1
        self._broadcast(item)

    def _on_live(self, plane: int, delivery: Any) -> None:
        try:
            live = decode_live(delivery.payload)
        except RejectedMessage as error:
            self._reject("live", error)
            return
        finally:
            delivery.ack()
        item = {"type": "live", **msgspec.to_builtins(live), "plane": plane}
        item.pop("schema", None)
        item["received_at"] = time.time()
        with self._lock:
            self._state[plane].last_live = item
            self.counters["live"] += 1
        self._broadcast(item)

    def _on_alert(self, plane: int, delivery: Any) -> None:
        try:
            alert = decode_alert(delivery.payload)
        except RejectedMessage as error:
            self._reject("alert", error)
            return
        finally:
            delivery.ack()
        item = {"type": "alert", **msgspec.to_builtins(alert), "plane": plane}
        item.pop("schema", None)
        key = (alert.episode, alert.state)
        with self._lock:
            alerts = self._state[plane].alerts
            if key in alerts:  # QoS 1, or the retained one again after a reconnection
                return
            alerts[key] = item
            while len(alerts) > RECENT_ALERTS:
                alerts.popitem(last=False)
            self.counters["alerts"] += 1
        self._broadcast(item)

    def _on_status(self, plane: int, delivery: Any) -> None:
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
            self._state[plane].status[camera] = online
        self._broadcast({"type": "status", "plane": plane, "camera": camera, "online": online})

    def _on_matcher(self, plane: int, delivery: Any) -> None:
        """A matcher's (plane 0: a linker's) availability."""
        try:
            status = decode_status(delivery.payload)
        except RejectedMessage as error:
            self._reject("matcher status", error)
            return
        finally:
            delivery.ack()
        name = delivery.topic.split("/")[-2]
        online = status.state == "online"
        with self._lock:
            self._state[plane].matchers[name] = online
        self._broadcast({"type": "matcher", "plane": plane, "matcher": name, "online": online})

    def _reject(self, what: str, error: Exception) -> None:
        with self._lock:
            self.counters["rejected"] += 1
        logger.warning("dashboard: ignored a %s message: %s", what, error)
