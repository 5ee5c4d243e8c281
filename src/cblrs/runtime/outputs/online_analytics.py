"""The analytics of one plane inside the matcher service: counted as the tracker commits.

:class:`OnlineAnalytics` runs the same engine as ``cblrs analytics``
(:class:`cblrs.analytics.Analytics`) on each tracker group's rows, in the matcher's tracker
process, and turns what it counted into writes for the group's own SQLite transaction
(:class:`cblrs.runtime.outputs.analytics_store.AnalyticsWrites`): the events (the outbox the
service publishes from), the increments of the persistent counters and the engine's state.
Tracks, events, counts and state are thus committed together, so a matcher killed at any
moment (SIGKILL) and restarted on its database resumes from a state that matches its counts:
nothing is counted twice and nothing is lost.

How it differs from the offline run, and why the counts are nevertheless the same:

* **time order.** The engine needs rows in time order. A tracker may return, for a released
  group, rows of earlier capture instants (clock-corrected windows of unsynchronised
  cameras), so rows wait behind the newest group time — ``delay_s`` plus the largest lag
  between a group's time and its earliest row seen so far — and are fed sorted.
  Empty groups advance the watermark too, so tracks that left end and their ``zone_left`` is
  reported while nothing else happens. Rows older than what was already fed are counted as
  late (``analytics_late_rows``), not silently merged.
* **aggregates.** After each batch the engine's aggregates (line counts, entries, visits,
  bins, OD) are moved into counter increments and cleared, so its state stays the size of
  the live tracks, however long the service runs; the totals live in the ``counts`` table.
* **end of stream.** :meth:`flush` (at the service's flushed stop, when the cameras said
  they are done) feeds every waiting row and ends every track, as the offline run does at
  the end of the file.
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Any

import msgspec
import numpy as np

from cblrs.analytics import Analytics, AnalyticsConfig, AnalyticsError, Event
from cblrs.analytics.config import LineCrossing, ZoneEntered, ZoneLeft
from cblrs.analytics.site import with_site_time
from cblrs.analytics.tables import class_name
from cblrs.detections import Tracks
from cblrs.places import Places
from cblrs.runtime.outputs.analytics_store import AnalyticsWrites, read_counts, read_state

ONLINE_STATE_VERSION = "cblrs.online-analytics/1"
DEFAULT_DELAY_S = 0.5
"""How long rows wait behind the newest capture time before they are counted, seconds."""

_ROW_FIELDS = ("frame", "timestamp", "track_id", "world_xy", "camera_id", "xyxy", "class_id")


def site_online_analytics(site: Any, plane_id: int,
                          delay_s: float = DEFAULT_DELAY_S) -> OnlineAnalytics | None:
    """The online analytics of one plane of a site (:class:`cblrs.site.Site`): its places
    on that plane, binned on the site's local clock and counted within its opening hours
    when it has them; None when the plane has no places."""
    places = plane_places(site.places, plane_id)
    if not len(places):
        return None
    return OnlineAnalytics(places, with_site_time(AnalyticsConfig(), site), delay_s=delay_s)


def plane_places(places: Places, plane_id: int) -> Places:
    """The places of one plane: those with ``plane_id`` None (every plane) or equal."""
    return Places(
        zones=tuple(zone for zone in places.zones if zone.plane_id in (None, plane_id)),
        lines=tuple(line for line in places.lines if line.plane_id in (None, plane_id)),
    )


class OnlineAnalytics:
    """Analytics of one plane, updated per tracker group (see the module docstring).

    Args:
        places: the plane's zones and counting lines (at least one).
        config: counting settings (the same defaults as ``cblrs analytics``); no heatmap.
        delay_s: rows wait this long behind the newest capture time.

    Raises:
        AnalyticsError: no places, or bad settings.

    Example:
        >>> from cblrs.places import CountingLine
        >>> online = OnlineAnalytics(Places(lines=(CountingLine("gate", (0, -5), (0, 5)),)))
        >>> walk = Tracks(np.arange(8), np.arange(8.0), np.ones(8, int),
        ...               np.c_[np.linspace(-4, 3, 8), np.zeros(8)])
        >>> [event.kind for event in online.update(walk, 7.0)]
        ['line_crossed']
    """

    def __init__(
        self,
        places: Places,
        config: AnalyticsConfig | None = None,
        delay_s: float = DEFAULT_DELAY_S,
    ):
        if not (math.isfinite(delay_s) and delay_s >= 0):
            raise AnalyticsError(f"the analytics delay must be a number >= 0, got {delay_s}.")
        config = config or AnalyticsConfig()
        if config.heatmap is not None:
            # A dense grid in every commit's state would cost more than the counts; heatmaps
            # come from ``cblrs analytics`` on the stored tracks.
            raise AnalyticsError("the online analytics keep no heatmap; leave heatmap unset.")
        self.engine = Analytics(places, config)
        self.delay_s = float(delay_s)
        self.log_increments = False
        """Also write each update's counter increments to ``count_log`` (with the update's
        time), so that a re-tracking can take back what was counted after a snapshot
        (:mod:`cblrs.runtime.matcher.retrack`); the tracker process sets it when it keeps
        snapshots."""
        self.log_floor = -math.inf
        """Increments are logged at a time above this (a re-tracking from a snapshot at
        ``t`` logs what it counts at ``t`` just after it, so a later one takes it back)."""
        self.reset()

    @property
    def places(self) -> Places:
        return self.engine.places

    def reset(self) -> None:
        """Forget everything learnt or tracked: back to the state of a new instance."""
        self.engine.reset()
        self._waiting = Tracks.empty()
        self._watermark = -math.inf
        self._lag = 0.0
        self._totals: dict[tuple[str, str], int] = defaultdict(int)
        self._writes = AnalyticsWrites()

    # ------------------------------------------------------------------ input
    def update(self, tracks: Tracks, timestamp: float) -> list[Event]:
        """Take one tracker group's rows; return the events that became final.

        Args:
            tracks: the group's rows (may be empty).
            timestamp: the group's watermark, seconds: the tracker has seen every message
                captured at or before it.
        """
        if len(tracks):
            self._waiting = Tracks.concatenate([self._waiting, tracks])
            newest = float(np.max(tracks.timestamp))
            # How far behind its group's time the tracker returns rows (clock-corrected
            # windows of unsynchronised cameras): rows wait that long too.
            self._lag = max(self._lag, float(timestamp) - float(np.min(tracks.timestamp)))
        else:
            newest = -math.inf
        self._watermark = max(self._watermark, float(timestamp), newest)
        cutoff = self._watermark - self.delay_s - self._lag
        ready = self._waiting.timestamp <= cutoff
        rows = self._waiting[ready]
        self._waiting = self._waiting[~ready]
        order = np.argsort(rows.timestamp, kind="stable")
        events = self.engine.update(rows[order], now=cutoff)
        self._collect(events, float(timestamp))
        return events

    def flush(self) -> list[Event]:
        """The end of the stream: count every waiting row, then end every track."""
        rows = self._waiting
        self._waiting = Tracks.empty()
        order = np.argsort(rows.timestamp, kind="stable")
        events = self.engine.update(rows[order])
        events += self.engine.flush()
        self._collect(events, self._watermark)
        return events

    # ------------------------------------------------------------------ output
    def take_writes(self) -> AnalyticsWrites:
        """What the updates since the last call add to the store, with the state after them.

        Call it once per tracker batch and commit the result in the batch's transaction.
        """
        writes, self._writes = self._writes, AnalyticsWrites()
        writes.state = self.get_state()
        return writes

    def live(self) -> dict[str, Any]:
        """Zones' occupancy and open visits' dwell now (confirmed tracks), and the clock."""
        clock = self.engine.clock
        return {
            "clock": None if math.isinf(clock) else clock,
            "occupancy": self.engine.live_occupancy(),
            "dwell": [[zone, track, seconds] for zone, track, seconds in self.engine.live_dwell()],
        }

    def _collect(self, events: list[Event], released: float) -> None:
        """Events to outbox rows (with running totals) and the engine's aggregates to counter
        increments (logged at ``released`` when :attr:`log_increments`); the aggregates are
        then cleared (their totals live in the store)."""
        writes = self._writes
        for event in events:
            writes.events.append(self._event_row(event))
        engine = self.engine
        logged: dict[tuple[str, tuple], float] = defaultdict(float)
        log = self.log_increments

        def add(table: str, key: tuple, value: float) -> None:
            getattr(writes, table)[key] += value  # term by term: the offline run's sums
            if log:
                logged[(table, key)] += value

        # A bin's key is its start in seconds: on the local clock with a site time zone.
        start = engine.bins.start
        for (line, direction, klass), value in engine.line_counts.items():
            add("counts", (line, direction, class_name(klass)), value)
        for (index, line, direction, klass), value in engine.line_bins.items():
            add("bins", (start(index), line, direction, class_name(klass)), value)
        for (index, zone, measure), value in engine.zone_bins.items():
            add("bins", (start(index), zone, measure, "all"), value)
        for (index, zone), seconds in engine.occupancy_seconds.items():
            add("bins", (start(index), zone, "occupancy_s", "all"), seconds)
        for (zone, klass), value in engine.zone_entries.items():
            add("counts", (zone, "entries", class_name(klass)), value)
        for (zone, klass), value in engine.zone_appeared.items():
            add("counts", (zone, "appeared", class_name(klass)), value)
        for visit in engine.visits:
            label = class_name(visit.class_id)
            add("counts", (visit.zone, "visits", label), 1)
            add("counts", (visit.zone, "dwell_s", label), visit.dwell_s)
            if visit.exited:
                add("counts", (visit.zone, "exits", label), 1)
            if visit.entered and visit.exited:
                add("counts", (visit.zone, "complete_visits", label), 1)
                add("counts", (visit.zone, "complete_dwell_s", label), visit.dwell_s)
        for key, value in engine.od.items():
            add("od", key, value)
        for zone, value in engine.od_unpaired.items():
            add("counts", (zone, "od_unpaired", "all"), value)
        for name, value in (("analytics_rows", engine.rows),
                            ("analytics_late_rows", engine.late_rows),
                            ("analytics_closed_events", engine.closed_events)):
            if value or name != "analytics_closed_events":
                writes.counters[name] = writes.counters.get(name, 0) + value
            if log and value:  # rows counted again after a re-tracking are counted once
                logged[("counters", (name,))] += value
        released = max(released, self.log_floor)
        writes.log += [(released, table, key, value)
                       for (table, key), value in logged.items() if value]
        for table in (engine.line_counts, engine.line_bins, engine.zone_bins, engine.zone_entries,
                      engine.zone_appeared, engine.occupancy_seconds, engine.od,
                      engine.od_unpaired):
            table.clear()
        engine.visits.clear()
        engine.rows = engine.late_rows = engine.closed_events = 0

    def _event_row(self, event: Event) -> tuple[float, str, str, int, str, str]:
        place = event_place(event)
        body: dict[str, Any] = {
            "kind": event.kind,
            "timestamp": event.timestamp,
            **self._local_time(event.timestamp),
            "track": event.track_id,
            "place": place,
        }
        if event.class_id >= 0:
            body["class"] = class_name(event.class_id)
        if isinstance(event, LineCrossing):
            total_key = (place, event.direction)
            body["direction"] = event.direction
            body["world_xy"] = list(event.world_xy)
        elif isinstance(event, ZoneEntered):
            total_key = (place, "visits_begun")
            body["crossed"] = event.crossed
        else:
            total_key = (place, "visits_ended")
            body.update(entered_at=event.entered_at, dwell_s=event.dwell_s,
                        entered=event.entered, exited=event.exited)
        self._totals[total_key] += 1
        body["total"] = self._totals[total_key]
        key = event_key(event)
        body["key"] = key
        return (event.timestamp, event.kind, place, event.track_id, key,
                msgspec.json.encode(body).decode())

    def _local_time(self, timestamp: float) -> dict[str, str]:
        calendar = self.engine.config.calendar
        return {} if calendar is None else {"time": calendar.iso(timestamp)}

    # ------------------------------------------------------------------ persistence
    def get_state(self) -> dict[str, Any]:
        """The engine's state (aggregates cleared), the waiting rows and the watermark."""
        return {
            "version": ONLINE_STATE_VERSION,
            "engine": self.engine.get_state(),
            "delay_s": self.delay_s,
            "watermark": None if math.isinf(self._watermark) else self._watermark,
            "lag_s": self._lag,
            "waiting": {name: getattr(self._waiting, name).tolist() for name in _ROW_FIELDS},
        }

    def set_state(self, state: dict[str, Any], counts: dict[tuple[str, str, str], float]) -> None:
        """Restore :meth:`get_state` and the running totals from the stored ``counts``.

        Raises:
            AnalyticsError: not such a state, or one made with other places or settings.
        """
        if not isinstance(state, dict) or state.get("version") != ONLINE_STATE_VERSION:
            raise AnalyticsError(
                f"the database holds no online analytics state (expected "
                f"{ONLINE_STATE_VERSION})."
            )
        if state.get("delay_s") != self.delay_s:
            raise AnalyticsError("the saved analytics state was made with another delay.")
        self.engine.set_state(state["engine"])
        watermark = state.get("watermark")
        self._watermark = -math.inf if watermark is None else float(watermark)
        self._lag = float(state.get("lag_s", 0.0))
        waiting = state["waiting"]
        self._waiting = Tracks(
            frame=np.asarray(waiting["frame"], np.int64),
            timestamp=np.asarray(waiting["timestamp"], np.float64),
            track_id=np.asarray(waiting["track_id"], np.int64),
            world_xy=np.asarray(waiting["world_xy"], np.float64).reshape(-1, 2),
            camera_id=np.asarray(waiting["camera_id"], np.int64),
            xyxy=np.asarray(waiting["xyxy"], np.float64).reshape(-1, 4),
            class_id=np.asarray(waiting["class_id"], np.int64),
        )
        self._totals = defaultdict(int, totals_from_counts(counts))
        self._writes = AnalyticsWrites()

    def resume(self, store: Any) -> bool:
        """Restore from a store (the tracker process's, at start); False if it holds none.

        Raises:
            AnalyticsError: the store's state was counted with other places or settings.
        """
        state = read_state(store)
        if state is None:
            self.reset()
            return False
        try:
            self.set_state(state, read_counts(store))
        except AnalyticsError as error:
            raise AnalyticsError(
                f"{store.path}: {error} Keep the site's places and analytics settings, or "
                "count anew in another --db."
            ) from None
        return True


def event_place(event: Event) -> str:
    """The name of the line or zone an analytics event is about."""
    if isinstance(event, LineCrossing):
        return event.line
    assert isinstance(event, ZoneEntered | ZoneLeft)
    return event.zone


def event_key(event: Event) -> str:
    """The natural identity of an event: ``kind/place/track/time`` (time as ``repr``), the
    same whenever the same tracks are counted again."""
    return f"{event.kind}/{event_place(event)}/{event.track_id}/{event.timestamp!r}"


def totals_from_counts(
    counts: dict[tuple[str, str, str], float],
) -> dict[tuple[str, str], int]:
    """Running totals of the event messages (summed over classes) from stored counters."""
    totals: dict[tuple[str, str], int] = defaultdict(int)
    for (place, measure, _), value in counts.items():
        if measure in ("positive", "negative"):
            totals[(place, measure)] += int(value)
        elif measure in ("entries", "appeared"):
            totals[(place, "visits_begun")] += int(value)
        elif measure == "visits":
            totals[(place, "visits_ended")] += int(value)
    return dict(totals)
