"""What the matcher service reports beyond tracks: analytics events, live summary, metrics.

:class:`ServiceReporter` is the part of
:class:`~cblrs.runtime.matcher.matcher_service.MatcherService` that turns its work into things
people watch; the service calls it at four points (a receiver batch stored, a tracker batch
committed, a camera status, start/stop) and it runs
two threads of its own:

* the **event outbox** publisher: events are committed by the tracker process in the same
  SQLite transaction as the tracks that produced them
  (:mod:`cblrs.runtime.outputs.online_analytics`); this thread publishes every event not yet marked
  published on ``cblrs/<plane>/events`` (QoS 1, in id order) and marks it once the broker
  acknowledged it. A matcher killed in between publishes it again after its restart:
  subscribers de-duplicate by the event's ``key``. Events never wait for the broker inside
  the tracker: a broker outage delays events, not tracking;
* the **live summary** publisher: about once a second, retained, on ``cblrs/<plane>/live``:
  the persistent counters (read from the store), the zones' occupancy and open visits'
  dwell (from the tracker process's engine), and each camera's health as received here
  (online, messages, rejections, rate, age of the last message).

It also feeds :class:`~cblrs.runtime.matcher.metrics.ServiceMetrics` when the service has one.
"""

from __future__ import annotations

import functools
import inspect
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from cblrs.runtime.matcher.metrics import ServiceMetrics
from cblrs.runtime.matcher.store import LATE
from cblrs.runtime.outputs.analytics_store import (
    count_summary,
    mark_published,
    read_counts,
    read_events,
)
from cblrs.runtime.outputs.events import encode_event, encode_live
from cblrs.runtime.transport.topics import (
    TopicError,
    events_topic,
    live_topic,
    parse_detections_topic,
)

logger = logging.getLogger(__name__)

_parse_detections_topic = functools.lru_cache(maxsize=4096)(parse_detections_topic)
"""Cached: a plane has few cameras, hence few topics (the receiver thread parses one per
message; a bad topic raises each time and is not kept)."""

RATE_WINDOW_S = 5.0
"""Camera message rates are averaged over this many seconds."""
ONLINE_SILENCE_S = 10.0
"""A camera not heard from for this long is shown offline (unless it said online since)."""
OUTBOX_BATCH = 500
ACK_TIMEOUT_S = 10.0


class CameraHealth:
    """Per camera: messages, rejections, recent rate, last capture and arrival, status."""

    def __init__(self, camera_ids: Iterable[str], monotonic: Callable[[], float] = time.monotonic):
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self.received: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self._arrivals: dict[str, deque[tuple[float, int]]] = {}
        self._last_arrival: dict[str, float] = {}
        self._last_capture: dict[str, float] = {}
        self._said: dict[str, bool] = {}
        self.cameras = list(camera_ids)

    def add(self, camera: str, received: int, rejected: int, last_capture: float | None) -> None:
        now = self._monotonic()
        with self._lock:
            if camera not in self.cameras:
                self.cameras.append(camera)
            self.received[camera] += received
            self.rejected[camera] += rejected
            arrivals = self._arrivals.setdefault(camera, deque())
            arrivals.append((now, received))
            self._last_arrival[camera] = now
            if last_capture is not None:
                self._last_capture[camera] = max(self._last_capture.get(camera, last_capture),
                                                 last_capture)

    def said(self, camera: str, online: bool) -> None:
        with self._lock:
            self._said[camera] = online
            if online:
                self._last_arrival.setdefault(camera, self._monotonic())

    def summary(self) -> list[dict[str, Any]]:
        now = self._monotonic()
        rows = []
        with self._lock:
            for camera in self.cameras:
                arrivals = self._arrivals.get(camera, deque())
                while arrivals and now - arrivals[0][0] > RATE_WINDOW_S:
                    arrivals.popleft()
                last = self._last_arrival.get(camera)
                age = None if last is None else now - last
                said = self._said.get(camera)
                online = said is not False and age is not None and (
                    age < ONLINE_SILENCE_S or said is True)
                rows.append({
                    "camera": camera,
                    "online": bool(online),
                    "received": int(self.received[camera]),
                    "rejected": int(self.rejected[camera]),
                    "rate_hz": sum(count for _, count in arrivals) / RATE_WINDOW_S,
                    "last_capture": self._last_capture.get(camera),
                    "last_age_s": age,
                })
        return rows


def _publish_with_result(transport: Any) -> bool:
    """Whether the transport reports each publish's broker answer (``on_result``)."""
    try:
        return "on_result" in inspect.signature(transport.publish).parameters
    except (TypeError, ValueError):
        return False


class ServiceReporter:
    """Events, live summary and metrics of one matcher service (see the module docstring).

    Args:
        transport: the service's transport (publishes events and the live summary).
        store: the service's store (its own connection, in the service process).
        plane_id: the plane.
        camera_ids: the plane's cameras.
        places: the analytics' places (None: no analytics, so no outbox and no counts).
        metrics: the service's metrics, or None.
        live_interval_s: seconds between live summaries (None: none).
    """

    def __init__(
        self,
        transport: Any,
        store: Any,
        plane_id: int,
        camera_ids: Iterable[str],
        places: Any = None,
        metrics: ServiceMetrics | None = None,
        live_interval_s: float | None = 1.0,
    ):
        self.transport = transport
        self.store = store
        self.plane_id = int(plane_id)
        self.places = places
        self.metrics = metrics
        self.live_interval_s = live_interval_s
        self.health = CameraHealth(camera_ids)
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._threads: list[threading.Thread] = []
        self._live: dict[str, Any] = {"clock": None, "occupancy": {}, "dwell": []}
        self._counts: dict[str, Any] = {"lines": {}, "zones": {}}
        self._lock = threading.Lock()
        self.published_events = 0
        self.failed_publishes = 0

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self.places is not None:
            self._refresh_counts()
            self._threads.append(threading.Thread(
                target=self._publish_events, name=f"cblrs-events-{self.plane_id}", daemon=True))
        if self.live_interval_s:
            self._threads.append(threading.Thread(
                target=self._publish_live, name=f"cblrs-live-{self.plane_id}", daemon=True))
        for thread in self._threads:
            thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Publish what is left of the outbox (within ``timeout``), then stop the threads."""
        self._stop.set()
        self._wake.set()
        deadline = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))

    # ------------------------------------------------------------------ service hooks
    def stored(
        self,
        batch: Iterable[tuple[str, Any, float]],
        accepted: list[tuple[Any, str, float]],
        inserted: list[bool],
        counters: Mapping[str, int],
        seconds: float,
    ) -> None:
        """A receiver batch was stored and acknowledged (the service's receiver thread).

        Args:
            batch: the deliveries ``(kind, delivery, received_at)``.
            accepted: ``(entry, status, received_at)`` of the valid messages.
            inserted: per accepted message, whether it was new (False: a duplicate).
            counters: the batch's ``received`` and ``rejected.<reason>`` counts.
            seconds: how long validating, storing and acknowledging took.
        """
        received: Counter[str] = Counter()
        for kind, delivery, _ in batch:
            # An empty payload is a camera clearing a retained message (`cblrs camera` does at
            # every start), not a message: the service neither counts nor rejects it.
            if kind != "detections" or not delivery.payload:
                continue
            try:
                _, camera = _parse_detections_topic(delivery.topic)
            except TopicError:
                continue
            received[camera] += 1
        kept: Counter[str] = Counter()
        newest: dict[str, float] = {}
        for entry, _, _ in accepted:
            kept[entry.camera_id] += 1
            newest[entry.camera_id] = max(newest.get(entry.camera_id, entry.timestamp),
                                          entry.timestamp)
        for camera, count in received.items():
            self.health.add(camera, count, count - kept[camera], newest.get(camera))
        if self.metrics is not None:
            totals = dict(counters)
            totals["duplicates"] = inserted.count(False)
            totals["late"] = sum(1 for (_, status, _), new in zip(accepted, inserted, strict=True)
                                 if new and status == LATE)
            self.metrics.stored(totals, received, seconds)

    def status(self, camera: str, online: bool) -> None:
        self.health.said(camera, online)

    def tracked(self, groups: list[tuple[float, int]], report: Mapping[str, Any] | None) -> None:
        """A tracker batch was committed (the service's collector thread).

        Args:
            groups: ``(timestamp, track rows)`` per group.
            report: the tracker process's report of the batch (durations, events, live).
        """
        report = report or {}
        events = report.get("events") or {}
        if report.get("live") is not None:
            with self._lock:
                self._live = report["live"]
        if events:
            self._refresh_counts()
            self._wake.set()
        if self.metrics is not None:
            self.metrics.tracked(groups, report.get("durations") or {}, events)

    def live_state(self) -> dict[str, Any]:
        """The tracker process's latest live state: ``clock``, ``occupancy`` (zone ->
        tracks inside) and ``dwell`` (``(zone, track, seconds)`` of the open visits)."""
        with self._lock:
            return dict(self._live)

    def summary(self) -> dict[str, Any]:
        """The live summary (``cblrs.live/1`` fields without the schema)."""
        with self._lock:
            live, counts = self._live, self._counts
        dwell: dict[str, list[tuple[int, float]]] = {}
        for zone, track, seconds in live.get("dwell", []):
            dwell.setdefault(zone, []).append((int(track), round(float(seconds), 2)))
        lines = [
            {"line": line.name, "positive": int(counts["lines"].get(line.name, {}).get(
                "positive", 0)), "negative": int(counts["lines"].get(line.name, {}).get(
                    "negative", 0))}
            for line in (self.places.lines if self.places is not None else ())
        ]
        zones = []
        for zone in (self.places.zones if self.places is not None else ()):
            row = counts["zones"].get(zone.name, {})
            visits = sorted(dwell.get(zone.name, []), key=lambda item: -item[1])[:1000]
            zones.append({
                "zone": zone.name,
                "occupancy": int(live.get("occupancy", {}).get(zone.name, 0)),
                "entries": int(row.get("entries", 0)),
                "exits": int(row.get("exits", 0)),
                "visits": int(row.get("visits", 0)),
                "mean_dwell_s": float(row.get("mean_dwell_s", 0.0)),
                "dwell": visits,
            })
        return {
            "plane": self.plane_id,
            "sent_at": time.time(),
            "clock": live.get("clock"),
            "cameras": self.health.summary(),
            "lines": lines,
            "zones": zones,
        }

    # ------------------------------------------------------------------ threads
    def _refresh_counts(self) -> None:
        counts = count_summary(read_counts(self.store))
        with self._lock:
            self._counts = counts
            occupancy = dict(self._live.get("occupancy", {}))
        if self.metrics is not None:
            self.metrics.set_counts(counts, occupancy)

    def _publish_live(self) -> None:
        topic = live_topic(self.plane_id)
        assert self.live_interval_s
        while not self._stop.wait(self.live_interval_s):
            try:
                summary = self.summary()
                self.transport.publish(topic, encode_live(summary), qos=0, retain=True)
                if self.metrics is not None:
                    occupancy = {row["zone"]: row["occupancy"] for row in summary["zones"]}
                    self.metrics.set_counts(self._counts, occupancy)
            except Exception:  # a viewer feed must never stop the matcher
                logger.exception("plane %d: could not publish the live summary", self.plane_id)

    def _publish_events(self) -> None:
        """Outbox thread: publish unpublished events in id order, mark them once acked."""
        with_result = _publish_with_result(self.transport)
        while True:
            stopping = self._stop.is_set()
            try:
                published = self._publish_pending(with_result)
            except Exception:
                logger.exception("plane %d: publishing events failed; retrying",
                                 self.plane_id)
                published = 0
            if stopping:
                return
            if not published:
                self._wake.wait(1.0)
                self._wake.clear()

    def _publish_pending(self, with_result: bool) -> int:
        pending = read_events(self.store, unpublished=True, limit=OUTBOX_BATCH)
        if self.metrics is not None:
            ((waiting,),) = self.store.query("SELECT COUNT(*) FROM events WHERE published = 0")
            self.metrics.set_unpublished(int(waiting))
        if not pending:
            return 0
        if not getattr(self.transport, "connected", True):
            return 0
        topic = events_topic(self.plane_id)
        started = time.perf_counter()
        acknowledged: list[int] = []
        if with_result:
            answers: dict[int, int] = {}
            done = threading.Condition()

            def result(identifier: int) -> Callable[[int], None]:
                def on_result(reason: int) -> None:
                    with done:
                        answers[identifier] = reason
                        done.notify_all()
                return on_result

            for stored in pending:
                self.transport.publish(topic, encode_event(stored.body, self.plane_id, stored.id),
                                       qos=1, on_result=result(stored.id))
            deadline = time.monotonic() + ACK_TIMEOUT_S
            with done:
                while len(answers) < len(pending) and time.monotonic() < deadline:
                    done.wait(0.1)
            for stored in pending:
                reason = answers.get(stored.id)
                if reason is None or reason >= 0x80 or reason < 0:
                    break  # keep the order: the rest goes again next time
                acknowledged.append(stored.id)
        else:
            for stored in pending:
                self.transport.publish(topic, encode_event(stored.body, self.plane_id, stored.id),
                                       qos=1)
            if self.transport.flush(ACK_TIMEOUT_S):
                acknowledged = [stored.id for stored in pending]
        if len(acknowledged) < len(pending):
            self.failed_publishes += len(pending) - len(acknowledged)
            logger.warning("plane %d: the broker did not acknowledge %d events; they are sent "
                           "again", self.plane_id, len(pending) - len(acknowledged))
        mark_published(self.store, acknowledged)
        self.published_events += len(acknowledged)
        if self.metrics is not None:
            self.metrics.published(time.perf_counter() - started)
        return len(acknowledged)
