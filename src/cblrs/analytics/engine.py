"""Incremental analytics on global tracks: one engine for offline files and live updates.

:class:`Analytics` takes track rows in time order, in chunks of any size — one matcher update
at a time online, a whole file offline — and keeps everything it needs between chunks in its
own state (:meth:`Analytics.get_state` / :meth:`Analytics.set_state`, JSON-serialisable). A
chunk is processed vectorised over its rows, places and tracks; only the resulting sparse
transitions (crossings, zone entries/exits, ends of tracks) go through a Python loop. The
result depends only on the rows, never on how they were chunked: the tests feed the same
tracks whole, row by row and in random chunks, with a state round-trip in between, and
compare every table.

How a track becomes counts (each rule also in :class:`AnalyticsConfig`):

* A track's rows are split into **lives** at gaps longer than ``lost_after_s``; nothing is
  counted across such a gap.
* **Lines** — per (track, line) the engine keeps the side the track was last *confirmed* on
  (farther than the hysteresis from the line). A crossing is a change of confirmed side,
  timed and placed where the track last crossed the line itself, and counted only when that
  point lies on the segment. Jitter inside the band changes nothing. With the ``side_change``
  rule (:class:`cblrs.places.LineRule`, common tools' rule) a position is confirmed on its side
  whenever it lies within the segment's extent, however close to the line, and the change of
  side counts wherever the line itself was crossed.
* **Zones** — the same with the signed distance to the zone's border. A visit starts at an
  entry (confirmed outside, then inside) or an appearance (first confirmed state inside),
  and ends at an exit or at the end of the life. An exit followed by a re-entry within
  ``merge_gap_s`` continues the visit. Dwell = end - start, with times at the border itself.
* **Confirmation** — the events of a life count only once it has lasted ``min_track_s``.
* **Opening hours** (``AnalyticsConfig.opening_hours``) — a final event counts only when the
  site was open at its time (a visit: when it began); others are counted in
  ``closed_events`` and nothing else.
* **Heatmap** — each step between consecutive rows of a life adds half its duration to the
  cell of each end (person-seconds).
* **Origin-destination** — per life, the zone of its first visit and of its last visit
  (lives with two or more visits); lives with one visit are counted as unpaired.

It stays one module because :class:`Analytics` keeps one state (per track: last position, zones,
dwell; per place: counts) that every chunk updates in one vectorised pass; the places, the
configuration and the tables are in their own modules.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cblrs.analytics.config import (
    AnalyticsConfig,
    AnalyticsError,
    Event,
    LineCrossing,
    ZoneEntered,
    ZoneLeft,
    event_from_dict,
    event_to_dict,
    json_round_trip,
)
from cblrs.detections import CLASS_NAMES, Tracks
from cblrs.places import LineRule, Places

STATE_VERSION = "cblrs.analytics-state/1"

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

# Order of simultaneous transitions of one track: exits before entries, ends last.
_EXIT, _ENTER, _APPEAR, _CROSS = 0, 1, 1, 2
_PERSON = CLASS_NAMES.index("person")


@dataclass
class _Visit:
    start: float
    crossed: bool
    class_id: int
    end: float = math.nan
    exited: bool = False


@dataclass
class _Trip:
    first_start: float
    first_zone: int
    last_start: float
    last_zone: int
    visits: int


class Analytics:
    """Line counts, zone visits, dwell, occupancy, origin-destination and heatmap, online.

    Example:
        >>> from cblrs.places import CountingLine, Places
        >>> places = Places(lines=(CountingLine("gate", (0, -5), (0, 5)),))
        >>> rows = Tracks(np.arange(6), np.arange(6.0), np.ones(6, int),
        ...               np.c_[np.linspace(3, -3, 6), np.zeros(6)])
        >>> engine = Analytics(places)
        >>> [event.direction for event in engine.update(rows)]
        ['positive']
    """

    def __init__(self, places: Places, config: AnalyticsConfig | None = None):
        if len(places) == 0:
            raise AnalyticsError(
                "the site has no places: add zones or counting lines under places: in the "
                "site file."
            )
        self.places = places
        self.config = config or AnalyticsConfig()
        self.bins = self.config.time_bins()
        self._calendar = self.config.calendar
        lines, zones = places.lines, places.zones
        self._line_start = np.array([line.start for line in lines]).reshape(-1, 2)
        self._line_normal = np.array([line.direction for line in lines]).reshape(-1, 2)
        along = np.array([line.end - line.start for line in lines]).reshape(-1, 2)
        self._line_along = along / np.maximum(np.sum(along * along, axis=1, keepdims=True), 1e-12)
        rules = self.config.line_rules(places)
        self._line_band = np.array([band for _, band in rules])
        self._line_side_change = np.array(
            [rule is LineRule.SIDE_CHANGE for rule, _ in rules], dtype=bool
        )
        self._zone_band = np.array(
            [
                self.config.zone_hysteresis_m if zone.hysteresis_m is None else zone.hysteresis_m
                for zone in zones
            ]
        )
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget every track and every count."""
        lines, zones = len(self.places.lines), len(self.places.zones)
        self.clock = -math.inf
        # Per live track, in slots: the vectorised part reads and writes these.
        self._slot: dict[int, int] = {}
        self._ids = np.zeros(0, np.int64)
        self._last_t = np.zeros(0)
        self._last_xy = np.zeros((0, 2))
        self._life_first_t = np.zeros(0)
        self._line_side = np.zeros((0, lines), np.int8)
        self._line_zc = np.zeros((0, lines), bool)
        self._line_zc_t = np.zeros((0, lines))
        self._line_zc_along = np.zeros((0, lines))
        self._zone_state = np.zeros((0, zones), np.int8)
        self._zone_zc = np.zeros((0, zones), bool)
        self._zone_zc_t = np.zeros((0, zones))
        # Per live track, sparse.
        self._confirmed: dict[int, bool] = {}
        self._held: dict[int, list[Event]] = {}
        self._open: dict[tuple[int, int], _Visit] = {}
        self._pending: dict[tuple[int, int], _Visit] = {}
        self._trips: dict[int, _Trip] = {}
        # Aggregates.
        self.rows = 0
        self.late_rows = 0
        self.closed_events = 0
        self.line_counts: dict[tuple[str, str, int], int] = defaultdict(int)
        self.line_bins: dict[tuple[int, str, str, int], int] = defaultdict(int)
        self.zone_bins: dict[tuple[int, str, str], int] = defaultdict(int)
        self.zone_entries: dict[tuple[str, int], int] = defaultdict(int)
        self.zone_appeared: dict[tuple[str, int], int] = defaultdict(int)
        self.visits: list[ZoneLeft] = []
        self.occupancy_seconds: dict[tuple[int, str], float] = defaultdict(float)
        self.od: dict[tuple[str, str], int] = defaultdict(int)
        self.od_unpaired: dict[str, int] = defaultdict(int)
        grid = self.config.heatmap
        self.heatmap = np.zeros(grid.shape if grid else (0, 0))
        self.heatmap_outside_s = 0.0

    # ------------------------------------------------------------------ input
    def update(self, tracks: Tracks, now: float | None = None) -> list[Event]:
        """Take the next rows (time order across calls) and return the events now final.

        Args:
            tracks: rows with ``timestamp`` (seconds) not earlier than any row given before;
                earlier rows, and a second row of a track at one time, are dropped and
                counted in ``late_rows``. An empty update just advances the clock.
            now: the current time, seconds (default: the newest row). Tracks unseen for
                ``lost_after_s`` by then have ended, and exits older than ``merge_gap_s``
                are final.

        Returns:
            Events that became final with this update (held ones of newly confirmed tracks
            included), in time order.
        """
        emitted: list[Event] = []
        self._out = emitted
        if len(tracks):
            self._process(tracks)
        latest = float(np.max(tracks.timestamp)) if len(tracks) else -math.inf
        clock = max(self.clock, latest, -math.inf if now is None else float(now))
        self._advance(clock)
        emitted.sort(key=lambda event: event.timestamp)
        return emitted

    def flush(self) -> list[Event]:
        """End every live track where it was last seen (the end of the data)."""
        emitted: list[Event] = []
        self._out = emitted
        for track in list(self._slot):
            self._end_life(track, float(self._last_t[self._slot[track]]))
        self._remove(list(self._slot))
        for key in sorted(self._pending):
            self._finish_pending(key)
        emitted.sort(key=lambda event: event.timestamp)
        return emitted

    # ------------------------------------------------------------------ core
    def _process(self, tracks: Tracks) -> None:
        time = tracks.timestamp
        keep = np.isfinite(time) & np.all(np.isfinite(tracks.world_xy), axis=1)
        keep &= time >= self.clock
        order = np.lexsort((np.arange(len(tracks)), time, tracks.track_id))
        order = order[keep[order]]
        track_id, time = tracks.track_id[order], time[order]
        # A track's rows must move forward in time: drop repeats and anything at or before
        # the track's last row of an earlier update.
        duplicate = np.zeros(len(order), dtype=bool)
        duplicate[1:] = (track_id[1:] == track_id[:-1]) & (time[1:] <= time[:-1])
        known = self._slots_of(track_id)
        if len(self._ids):
            duplicate |= (known >= 0) & (time <= self._last_t[np.maximum(known, 0)])
        self.late_rows += len(tracks) - int(np.count_nonzero(~duplicate))
        order, track_id, time, known = (
            order[~duplicate], track_id[~duplicate], time[~duplicate], known[~duplicate]
        )
        self.rows += len(order)
        if not len(order):
            return
        xy = tracks.world_xy[order]
        class_id = tracks.class_id[order]

        # Lives whose stored part ended in the gap before this chunk end first.
        first = np.ones(len(order), dtype=bool)
        first[1:] = track_id[1:] != track_id[:-1]
        if len(self._ids):
            gone = first & (known >= 0)
            gone &= time - self._last_t[np.maximum(known, 0)] > self.config.lost_after_s
            for track in track_id[gone].tolist():
                self._end_life(track, float(self._last_t[self._slot[track]]))
            self._remove(track_id[gone].tolist())
            known = self._slots_of(track_id)

        # One virtual row per continuing track carries its stored state into the chunk.
        continuing = first & (known >= 0)
        slots = known[continuing]
        count = len(order) + len(slots)
        at = np.flatnonzero(continuing) + np.arange(len(slots))  # positions of virtual rows
        virtual = np.zeros(count, dtype=bool)
        virtual[at] = True
        real = ~virtual
        all_track = np.empty(count, np.int64)
        all_time = np.empty(count)
        all_xy = np.empty((count, 2))
        all_class = np.full(count, -1, np.int64)
        all_track[real], all_time[real], all_xy[real], all_class[real] = (
            track_id, time, xy, class_id
        )
        all_track[virtual] = self._ids[slots]
        all_time[virtual] = self._last_t[slots]
        all_xy[virtual] = self._last_xy[slots]

        boundary = np.ones(count, dtype=bool)
        step_s = all_time[1:] - all_time[:-1]
        step_m = np.hypot(*(all_xy[1:] - all_xy[:-1]).T)
        limit = np.where(all_class[1:] == _PERSON, self.config.max_person_speed_m_s,
                         self.config.max_speed_m_s)
        boundary[1:] = (all_track[1:] != all_track[:-1]) | (step_s > self.config.lost_after_s) | (
            step_m > limit * step_s
        )
        segment = np.cumsum(boundary) - 1
        segment_start = np.flatnonzero(boundary)
        segment_end = np.append(segment_start[1:], count) - 1
        segment_track = all_track[segment_start]
        segment_continued = virtual[segment_start]
        life_first = all_time[segment_start].copy()
        life_first[segment_continued] = self._life_first_t[slots]
        stored_confirmed = np.zeros(len(segment_start), dtype=bool)
        stored_confirmed[segment_continued] = [
            self._confirmed.get(int(track), False) for track in self._ids[slots]
        ]
        lived = np.maximum.reduceat(all_time, segment_start) - life_first
        segment_confirmed = stored_confirmed | (lived >= self.config.min_track_s)
        # A segment ends inside the chunk when the same track goes on in a later one.
        segment_ended = np.zeros(len(segment_start), dtype=bool)
        segment_ended[:-1] = segment_track[1:] == segment_track[:-1]

        # Each track's state after its last row of the chunk goes to its slot.
        self._allocate(segment_track[~segment_ended].tolist())
        self._store_rows = segment_end[~segment_ended]
        self._store_slots = np.array(
            [self._slot[int(track)] for track in segment_track[~segment_ended]], np.int64
        )
        previous = np.maximum(np.arange(count) - 1, 0)
        steps = ~boundary
        events: list[tuple[int, float, int, Any]] = []
        if len(self.places.lines):
            self._line_transitions(
                all_xy, all_time, all_class, all_track, boundary, virtual, previous, slots,
                segment, events,
            )
        if len(self.places.zones):
            self._zone_transitions(
                all_xy, all_time, all_class, all_track, boundary, virtual, previous, slots,
                segment, life_first, events,
            )
        if self.config.heatmap is not None:
            self._add_heatmap(all_xy[previous[steps]], all_xy[steps],
                              all_time[steps] - all_time[previous[steps]])

        events.sort(key=lambda item: (item[0], item[1], item[2]))
        cursor = 0
        for index in range(len(segment_start)):
            track = int(segment_track[index])
            if not segment_continued[index]:
                self._held[track] = []
            self._set_confirmed(track, bool(segment_confirmed[index]))
            while cursor < len(events) and events[cursor][0] == index:
                self._apply(track, events[cursor][3])
                cursor += 1
            if segment_ended[index]:
                self._end_life(track, float(all_time[segment_end[index]]))

        final = ~segment_ended
        rows, target = segment_end[final], self._store_slots
        self._last_t[target] = all_time[rows]
        self._last_xy[target] = all_xy[rows]
        self._life_first_t[target] = life_first[final]

    def _line_transitions(self, xy, time, class_id, track, boundary, virtual, previous, slots,
                          segment, events) -> None:
        distance = (xy @ self._line_normal.T) - np.sum(
            self._line_start * self._line_normal, axis=1
        )[None, :]
        confirmed = np.where(
            distance > self._line_band, 1, np.where(distance < -self._line_band, -1, 0)
        ).astype(np.int8)
        # Position along each line: 0 at its start, 1 at its end.
        along = (xy @ self._line_along.T) - np.sum(
            self._line_start * self._line_along, axis=1
        )[None, :]
        if self._line_side_change.any():
            # Common tools' rule: the side of any position within the segment's extent.
            within = (along >= 0) & (along <= 1)
            plain = np.where(within, np.where(distance >= 0, 1, -1), 0).astype(np.int8)
            confirmed = np.where(self._line_side_change[None, :], plain, confirmed)
        confirmed[virtual] = self._line_side[slots]
        side = np.take_along_axis(confirmed, _fill_index(confirmed != 0, boundary), axis=0)
        before = side[previous]
        before[boundary] = 0
        # Where the track crossed the line itself, between consecutive rows of a life.
        d0, d1 = distance[previous], distance
        crossing = ~boundary[:, None] & ((d0 >= 0) != (d1 >= 0))
        with np.errstate(divide="ignore", invalid="ignore"):
            fraction = np.where(crossing, d0 / (d0 - d1), 0.0)
        zc_t = time[previous][:, None] + fraction * (time - time[previous])[:, None]
        # Position along each line is linear in the point, so interpolate it directly.
        zc_along = along[previous] + fraction * (along - along[previous])
        crossing[virtual] = self._line_zc[slots]
        zc_t[virtual] = self._line_zc_t[slots]
        zc_along[virtual] = self._line_zc_along[slots]
        last_zc = _fill_index(crossing, boundary)
        has = np.take_along_axis(crossing, last_zc, axis=0)
        at_t = np.take_along_axis(zc_t, last_zc, axis=0)
        at_along = np.take_along_axis(zc_along, last_zc, axis=0)
        changed = ~boundary[:, None] & (side != 0) & (before != 0) & (side != before)
        # The hysteresis rule counts a crossing of the segment itself; the side-change rule
        # a change of side seen within the segment's extent, wherever the line was crossed.
        on_segment = (at_along >= 0) & (at_along <= 1)
        counted = changed & has & (on_segment | self._line_side_change[None, :])
        names = [line.name for line in self.places.lines]
        for row, line in zip(*(np.nonzero(counted)[axis].tolist() for axis in (0, 1)),
                             strict=True):
            crossed_at = float(at_t[row, line])
            fraction_along = float(at_along[row, line])
            place = self._line_start[line] + fraction_along * (
                self.places.lines[line].end - self.places.lines[line].start
            )
            event = LineCrossing(
                names[line], int(track[row]),
                crossed_at, "positive" if side[row, line] > 0 else "negative",
                int(class_id[row]), (float(place[0]), float(place[1])),
            )
            events.append((int(segment[row]), crossed_at, _CROSS, event))
        rows, target = self._store_rows, self._store_slots
        self._line_side[target] = side[rows]
        self._line_zc[target] = has[rows]
        self._line_zc_t[target] = at_t[rows]
        self._line_zc_along[target] = at_along[rows]

    def _zone_transitions(self, xy, time, class_id, track, boundary, virtual, previous, slots,
                          segment, life_first, events) -> None:
        distance = np.stack([zone.signed_distance(xy) for zone in self.places.zones], axis=1)
        confirmed = np.where(
            distance > self._zone_band, 1, np.where(distance < -self._zone_band, -1, 0)
        ).astype(np.int8)
        confirmed[virtual] = self._zone_state[slots]
        state = np.take_along_axis(confirmed, _fill_index(confirmed != 0, boundary), axis=0)
        before = state[previous]
        before[boundary] = 0
        d0, d1 = distance[previous], distance
        crossing = ~boundary[:, None] & ((d0 > 0) != (d1 > 0))
        with np.errstate(divide="ignore", invalid="ignore"):
            fraction = np.where(crossing, d0 / (d0 - d1), 0.0)
        zc_t = time[previous][:, None] + fraction * (time - time[previous])[:, None]
        crossing[virtual] = self._zone_zc[slots]
        zc_t[virtual] = self._zone_zc_t[slots]
        last_zc = _fill_index(crossing, boundary)
        has = np.take_along_axis(crossing, last_zc, axis=0)
        at_t = np.take_along_axis(zc_t, last_zc, axis=0)
        starts = (state == 1) & (before != 1) & ~virtual[:, None]
        exits = (state == -1) & (before == 1)
        for row, zone in zip(*(np.nonzero(starts | exits)[axis].tolist() for axis in (0, 1)),
                             strict=True):
            index = int(segment[row])
            if state[row, zone] == 1:
                crossed = bool(before[row, zone] == -1)
                if has[row, zone]:
                    start = float(at_t[row, zone])
                elif boundary[row]:
                    start = float(time[row])
                else:
                    start = float(life_first[index])
                events.append((index, start, _ENTER, ("start", zone, start, crossed,
                                                      int(class_id[row]))))
            else:
                end = float(at_t[row, zone])
                events.append((index, end, _EXIT, ("stop", zone, end)))

        rows, target = self._store_rows, self._store_slots
        self._zone_state[target] = state[rows]
        self._zone_zc[target] = has[rows]
        self._zone_zc_t[target] = at_t[rows]

    # ------------------------------------------------------------------ visits
    def _apply(self, track: int, item: Any) -> None:
        if isinstance(item, LineCrossing):
            self._emit(track, item)
            return
        if item[0] == "start":
            _, zone, start, crossed, class_id = item
            key = (track, zone)
            pending = self._pending.get(key)
            if pending is not None and start - pending.end <= self.config.merge_gap_s:
                del self._pending[key]
                self._open[key] = _Visit(pending.start, pending.crossed, pending.class_id)
                return
            if pending is not None:
                self._finish_pending(key)
            self._open[key] = _Visit(start, crossed, class_id)
            self._emit(track, ZoneEntered(self.places.zones[zone].name, track, start, crossed,
                                          class_id))
        else:
            _, zone, end = item
            visit = self._open.pop((track, zone), None)
            if visit is not None:
                visit.end, visit.exited = end, True
                self._pending[(track, zone)] = visit

    def _finish_pending(self, key: tuple[int, int]) -> None:
        visit = self._pending.pop(key)
        self._emit(key[0], _left(self.places.zones[key[1]].name, key[0], visit))

    def _end_life(self, track: int, last_t: float) -> None:
        for key in [key for key in self._open if key[0] == track]:
            visit = self._open.pop(key)
            visit.end, visit.exited = last_t, False
            self._emit(track, _left(self.places.zones[key[1]].name, track, visit))
        for key in sorted(key for key in self._pending if key[0] == track):
            self._finish_pending(key)
        self._held.pop(track, None)  # never confirmed: its events do not count
        trip = self._trips.pop(track, None)
        if trip is not None:
            names = [zone.name for zone in self.places.zones]
            if trip.visits >= 2:
                self.od[(names[trip.first_zone], names[trip.last_zone])] += 1
            else:
                self.od_unpaired[names[trip.first_zone]] += 1
        self._confirmed.pop(track, None)

    def _set_confirmed(self, track: int, confirmed: bool) -> None:
        self._confirmed[track] = confirmed
        if confirmed:
            for event in self._held.pop(track, []):
                self._count(event)

    def _emit(self, track: int, event: Event) -> None:
        if self._confirmed.get(track, False):
            self._count(event)
        else:
            self._held.setdefault(track, []).append(event)

    def _count(self, event: Event) -> None:
        """Add a final event to the aggregates and to this call's output."""
        if not self._open_at(event.entered_at if isinstance(event, ZoneLeft)
                             else event.timestamp):
            self.closed_events += 1
            return
        key = self.bins.key
        if isinstance(event, LineCrossing):
            self.line_counts[(event.line, event.direction, event.class_id)] += 1
            bin_index = key(event.timestamp)
            self.line_bins[(bin_index, event.line, event.direction, event.class_id)] += 1
        elif isinstance(event, ZoneEntered):
            table = self.zone_entries if event.crossed else self.zone_appeared
            table[(event.zone, event.class_id)] += 1
            if event.crossed:
                self.zone_bins[(key(event.timestamp), event.zone, "entries")] += 1
        else:
            self.visits.append(event)
            if event.exited:
                self.zone_bins[(key(event.timestamp), event.zone, "exits")] += 1
            self._add_occupancy(event.zone, event.entered_at, event.timestamp)
            zone = [zone.name for zone in self.places.zones].index(event.zone)
            trip = self._trips.get(event.track_id)
            if trip is None:
                self._trips[event.track_id] = _Trip(
                    event.entered_at, zone, event.entered_at, zone, 1
                )
            else:
                trip.visits += 1
                if (event.entered_at, zone) < (trip.first_start, trip.first_zone):
                    trip.first_start, trip.first_zone = event.entered_at, zone
                if (event.entered_at, zone) >= (trip.last_start, trip.last_zone):
                    trip.last_start, trip.last_zone = event.entered_at, zone
        self._out.append(event)

    def _add_occupancy(self, zone: str, start: float, end: float,
                       table: dict[tuple[int, str], float] | None = None) -> None:
        table = self.occupancy_seconds if table is None else table
        bins = self.bins
        bin_index, last = bins.key(start), bins.key(end)
        while True:
            low = max(start, bins.start(bin_index))
            high = min(end, bins.end(bin_index))
            if high > low:
                table[(bin_index, zone)] += high - low
            if bin_index >= last:
                break
            bin_index = bins.following(bin_index)

    def _open_at(self, timestamp: float) -> bool:
        return self._calendar is None or self._calendar.is_open(timestamp)

    def _add_heatmap(self, before: FloatArray, after: FloatArray, seconds: FloatArray) -> None:
        grid = self.config.heatmap
        assert grid is not None
        rows, columns = grid.shape
        points = np.concatenate([before, after])
        weights = np.concatenate([seconds, seconds]) / 2.0
        column = np.floor((points[:, 0] - grid.origin[0]) / grid.cell_m).astype(np.int64)
        row = np.floor((points[:, 1] - grid.origin[1]) / grid.cell_m).astype(np.int64)
        inside = (column >= 0) & (column < columns) & (row >= 0) & (row < rows)
        self.heatmap += np.bincount(
            row[inside] * columns + column[inside], weights[inside], minlength=rows * columns
        ).reshape(rows, columns)
        self.heatmap_outside_s += float(weights[~inside].sum())

    # ------------------------------------------------------------------ clock
    def _advance(self, clock: float) -> None:
        self.clock = clock
        if self._slot:
            lost = np.flatnonzero(clock - self._last_t > self.config.lost_after_s)
            tracks = self._ids[lost].tolist()
            for track in tracks:
                self._end_life(track, float(self._last_t[self._slot[track]]))
            self._remove(tracks)
        for key in sorted(self._pending):
            if clock - self._pending[key].end > self.config.merge_gap_s:
                self._finish_pending(key)

    # ------------------------------------------------------------------ slots
    def _slots_of(self, track_id: IntArray) -> IntArray:
        """Slot of each row's track, -1 for tracks without one."""
        if not self._slot:
            return np.full(len(track_id), -1, np.int64)
        return np.array([self._slot.get(track, -1) for track in track_id.tolist()], np.int64)

    def _allocate(self, tracks: list[int]) -> None:
        """Give every track in ``tracks`` that has none a zeroed slot (one append for all)."""
        new = [track for track in dict.fromkeys(tracks) if track not in self._slot]
        if not new:
            return
        for offset, track in enumerate(new):
            self._slot[track] = len(self._ids) + offset
        count = len(new)
        for name in self._SLOT_ARRAYS:
            array = getattr(self, name)
            extra = np.zeros((count, *array.shape[1:]), array.dtype)
            setattr(self, name, np.concatenate([array, extra]))
        self._ids[-count:] = new

    _SLOT_ARRAYS = ("_ids", "_last_t", "_last_xy", "_life_first_t", "_line_side", "_line_zc",
                    "_line_zc_t", "_line_zc_along", "_zone_state", "_zone_zc", "_zone_zc_t")

    def _remove(self, tracks: Iterable[int]) -> None:
        drop = [self._slot.pop(int(track)) for track in tracks if int(track) in self._slot]
        if not drop:
            return
        keep = np.ones(len(self._ids), dtype=bool)
        keep[drop] = False
        for name in self._SLOT_ARRAYS:
            setattr(self, name, getattr(self, name)[keep])
        self._slot = {int(track): slot for slot, track in enumerate(self._ids.tolist())}

    # ------------------------------------------------------------------ persistence
    def get_state(self) -> dict[str, Any]:
        """Everything the engine remembers, JSON-serialisable (restore with :meth:`set_state`)."""
        return {
            "version": STATE_VERSION,
            "places": self.places.to_dict(),
            "config": self.config.to_dict(),
            "clock": None if math.isinf(self.clock) else self.clock,
            "slots": {name: getattr(self, name).tolist() for name in self._SLOT_ARRAYS},
            "confirmed": [[track, value] for track, value in self._confirmed.items()],
            "held": [[track, [event_to_dict(event) for event in events]]
                     for track, events in self._held.items()],
            "open": [[*key, asdict(visit)] for key, visit in self._open.items()],
            "pending": [[*key, asdict(visit)] for key, visit in self._pending.items()],
            "trips": [[track, asdict(trip)] for track, trip in self._trips.items()],
            "rows": self.rows,
            "late_rows": self.late_rows,
            "closed_events": self.closed_events,
            "line_counts": [[*key, value] for key, value in self.line_counts.items()],
            "line_bins": [[*key, value] for key, value in self.line_bins.items()],
            "zone_bins": [[*key, value] for key, value in self.zone_bins.items()],
            "zone_entries": [[*key, value] for key, value in self.zone_entries.items()],
            "zone_appeared": [[*key, value] for key, value in self.zone_appeared.items()],
            "visits": [event_to_dict(event) for event in self.visits],
            "occupancy_seconds": [[*key, value] for key, value in self.occupancy_seconds.items()],
            "od": [[*key, value] for key, value in self.od.items()],
            "od_unpaired": [[key, value] for key, value in self.od_unpaired.items()],
            "heatmap": self.heatmap.tolist(),
            "heatmap_outside_s": self.heatmap_outside_s,
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """Restore a snapshot of :meth:`get_state` taken with the same places and settings.

        Raises:
            AnalyticsError: not such a snapshot, or one for other places or settings.
        """
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise AnalyticsError(f"not a saved analytics state (expected {STATE_VERSION}).")
        if state.get("places") != json_round_trip(self.places.to_dict()):
            raise AnalyticsError("the saved analytics state is for other places.")
        saved = state.get("config")
        if isinstance(saved, dict) and "line_rule" not in saved:
            # Saved before lines had a rule: they were all counted with the hysteresis rule.
            saved = {**saved, "line_rule": LineRule.HYSTERESIS.value}
        if isinstance(saved, dict):
            # Saved before sites had local time: bins from time 0, always open.
            saved = {"timezone": None, "opening_hours": None, **saved}
        if saved != json_round_trip(self.config.to_dict()):
            raise AnalyticsError("the saved analytics state was made with other settings.")
        try:
            self.reset()
            self.clock = -math.inf if state["clock"] is None else float(state["clock"])
            templates = {name: getattr(self, name) for name in self._SLOT_ARRAYS}
            count = len(state["slots"]["_ids"])
            for name, template in templates.items():
                value = np.asarray(state["slots"][name], dtype=template.dtype)
                # The row count is explicit: a site without zones (or lines) has (N, 0)
                # columns, which -1 cannot infer.
                setattr(self, name, value.reshape((count, *template.shape[1:])))
            self._slot = {int(track): slot for slot, track in enumerate(self._ids.tolist())}
            self._confirmed = {int(track): bool(value) for track, value in state["confirmed"]}
            self._held = {int(track): [event_from_dict(item) for item in events]
                          for track, events in state["held"]}
            self._open = {(int(t), int(z)): _Visit(**visit) for t, z, visit in state["open"]}
            self._pending = {(int(t), int(z)): _Visit(**visit)
                             for t, z, visit in state["pending"]}
            self._trips = {int(track): _Trip(**trip) for track, trip in state["trips"]}
            self.rows, self.late_rows = int(state["rows"]), int(state["late_rows"])
            self.closed_events = int(state.get("closed_events", 0))
            for name, width in (("line_counts", 3), ("line_bins", 4), ("zone_bins", 3),
                                ("zone_entries", 2), ("zone_appeared", 2),
                                ("occupancy_seconds", 2), ("od", 2)):
                table = getattr(self, name)
                for item in state[name]:
                    table[tuple(item[:width])] = item[width]
            for key, value in state["od_unpaired"]:
                self.od_unpaired[key] = int(value)
            self.visits = [event_from_dict(item) for item in state["visits"]]  # type: ignore[misc]
            self.heatmap = np.asarray(state["heatmap"], np.float64).reshape(self.heatmap.shape)
            self.heatmap_outside_s = float(state["heatmap_outside_s"])
        except (KeyError, TypeError, ValueError) as error:
            raise AnalyticsError(f"the saved analytics state is incomplete: {error}.") from None

    # ------------------------------------------------------------------ live view
    def live_occupancy(self) -> dict[str, int]:
        """Tracks inside each zone now (open visits of confirmed tracks, begun while open)."""
        counts = {zone.name: 0 for zone in self.places.zones}
        for (track, zone), visit in self._open.items():
            if self._confirmed.get(track, False) and self._open_at(visit.start):
                counts[self.places.zones[zone].name] += 1
        return counts

    def live_dwell(self) -> list[tuple[str, int, float]]:
        """(zone, track, seconds so far) of every open visit of a confirmed track."""
        return [
            (self.places.zones[zone].name, track, self.clock - visit.start)
            for (track, zone), visit in sorted(self._open.items())
            if self._confirmed.get(track, False) and self._open_at(visit.start)
        ]


def _fill_index(valid: BoolArray, boundary: BoolArray) -> IntArray:
    """Per column, the index of the last row <= each row where ``valid`` holds, not looking
    back past a ``boundary`` row (which points at itself when nothing is valid)."""
    rows = np.arange(len(valid))[:, None]
    index = np.where(valid | boundary[:, None], rows, -1)
    return np.maximum.accumulate(index, axis=0)


def _left(zone: str, track: int, visit: _Visit) -> ZoneLeft:
    return ZoneLeft(zone, track, visit.start, visit.end, visit.end - visit.start, visit.crossed,
                    visit.exited, visit.class_id)
