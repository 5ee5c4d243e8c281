"""Late data is tracked: snapshots of the tracker, and re-tracking from one.

A message that reaches the matcher service after its window was released (a camera
re-sending its spool after a broker outage, a camera that stalled, a restarted matcher) is
stored as ``late`` (:mod:`cblrs.runtime.matcher.ordering`). The service's tracker process
(:mod:`cblrs.runtime.matcher.tracker_process`) then tracks it by going back in time:

1. **snapshots**: with the commit of a group whose watermark (released timestamp) is at
   least ``snapshot_interval_s`` of capture time after the last snapshot, the matcher's
   state is also saved in the ``snapshots`` table, with the last track row written so far
   and the keys of the messages processed *at* the watermark (ties, so the re-tracked
   messages are exactly those the snapshot has not seen). A fresh database gets one
   snapshot of the empty tracker. Snapshots older than ``horizon_s`` behind the newest, and
   beyond the newest ``max_snapshots``, are deleted in the same transaction;
2. **re-tracking**, asked for by the service once no late message has arrived for
   ``delay_s`` (so a burst of re-sends is handled once): the newest snapshot strictly
   before the earliest new late message is restored; every inbox message after it
   (``processed`` and the new ``late`` ones) is ordered again into windows
   (:class:`~cblrs.runtime.matcher.ordering.Orderer`) and tracked; the matcher's watermark is then
   advanced to the last released timestamp, as the undisturbed run's was. One transaction
   replaces the track rows written after the snapshot with the re-tracked ones, marks the
   late messages ``processed``, replaces the later snapshots with new ones taken during the
   re-tracking and saves the matcher state;
3. the re-tracked windows are published as track updates with ``corrected_from``: the
   snapshot's time — they replace every row after it that earlier updates carried.

The fusion tracker fuses messages in windows of clock-corrected capture time, whatever
windows the ordering releases them in (:mod:`cblrs.runtime.matcher.ordering`), so the re-tracked
rows are the rows of a run that had every message in time.

Late messages at or before the oldest snapshot cannot be re-tracked: they stay ``late`` and
are counted as ``late_untracked``. Counters: ``retracks`` (re-trackings done),
``retracked`` (messages tracked again), ``late_tracked`` (late messages now tracked),
``late_untracked``.

The online analytics follow the correction (:mod:`cblrs.runtime.outputs.online_analytics`): a
snapshot also holds the analytics' state and the last event id then, and every counter
increment is logged with its group's time (``count_log``). A re-tracking takes back, in the
same transaction, the increments logged after the snapshot and the events after its id
(:func:`~cblrs.runtime.outputs.analytics_store.roll_back`), restores the analytics' state and counts
the re-tracked rows again: counts, bins and origin-destination equal the undisturbed run's
(sums of seconds up to float rounding), and so do the events. An event found again that was
already published keeps its key and is not published twice; a published event the
correction no longer finds is taken back by an ``event_retracted`` event naming its key.
Snapshots of a database written before the analytics were snapshotted hold no analytics
state: their events and counts stay as counted (``analytics_uncorrected``).
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.runtime.matcher.ordering import Orderer
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_rows import INSERT_TRACKS, InboxEntry, track_rows
from cblrs.runtime.matcher.store_schema import (
    LATE,
    PROCESSED,
    add_counter_values,
    check_tracker,
    set_matcher_state,
    set_meta_value,
)
from cblrs.runtime.outputs.analytics_store import (
    keep_published,
    prune_log,
    read_counts,
    roll_back,
)

SNAPSHOTS_SCHEMA = """
CREATE TABLE IF NOT EXISTS snapshots (
    released REAL PRIMARY KEY,
    track_row INTEGER NOT NULL,
    boundary TEXT NOT NULL,
    state TEXT NOT NULL,
    event_row INTEGER,
    analytics TEXT
)
"""
"""``released``: the watermark of the last group the state has seen (-inf: none);
``track_row``: the last track row written then; ``boundary``: JSON ``[[camera, sequence],
...]`` of the messages at ``released`` already tracked; ``state``: ``get_state()`` JSON;
``event_row``: the last analytics event id then; ``analytics``: the online analytics'
``get_state()`` JSON (NULL: no analytics, or a snapshot from before they were kept)."""

DELETED_KEY = "deleted_until.inbox"
"""Meta key (:mod:`cblrs.runtime.matcher.retention`): the newest capture time of a deleted
inbox row."""

SEEN_KEY = "retrack_seen_rowid"
"""Meta key: the highest inbox rowid of a late message a re-tracking has looked at."""


@dataclass(frozen=True)
class RetrackPolicy:
    """When snapshots are taken and late messages re-tracked.

    Attributes:
        snapshot_interval_s: capture-time seconds between snapshots.
        horizon_s: snapshots are kept this many capture-time seconds behind the newest; a
            late message older than the oldest snapshot stays untracked.
        max_snapshots: at most this many snapshots are kept.
        delay_s: re-track once no late message has arrived for this long (service clock,
            seconds), so a burst of re-sends is re-tracked once.
    """

    snapshot_interval_s: float = 5.0
    horizon_s: float = 600.0
    max_snapshots: int = 240
    delay_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("snapshot_interval_s", "horizon_s", "delay_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise CblrsError(f"re-tracking {name} must be a finite number >= 0, got {value}.")
        if self.max_snapshots < 1:
            raise CblrsError(f"re-tracking keeps at least one snapshot, got {self.max_snapshots}.")


@dataclass
class Retracked:
    """What one re-tracking did.

    Attributes:
        windows: ``(timestamp, tracks)`` per re-tracked window, in time order.
        corrected_from: the snapshot's time: these rows replace every row after it; None
            when nothing was re-tracked.
        counters: counter increments (committed).
        events: analytics events counted again, by kind.
    """

    windows: list[tuple[float, Tracks]] = field(default_factory=list)
    corrected_from: float | None = None
    counters: dict[str, int] = field(default_factory=dict)
    events: dict[str, int] = field(default_factory=dict)


class Snapshots:
    """The tracker process's snapshots in its store (see the module docstring).

    Args:
        store: the tracker process's store (the table is created when missing).
        policy: when to take and how long to keep them.
    """

    def __init__(self, store: RuntimeStore, policy: RetrackPolicy):
        self.store = store
        self.policy = policy
        store.write(_create_table)
        rows = store.query("SELECT MAX(released) FROM snapshots")
        self._last: float | None = None if rows[0][0] is None else float(rows[0][0])

    def start(self, state: Any, analytics: Any = None) -> None:
        """A fresh database: snapshot the empty tracker (late messages of the first
        windows are re-tracked from it); ``analytics``: the online analytics' state."""
        if self._last is None and self.store.released_timestamp() is None:
            self.taking(-math.inf)
            self.store.write(lambda cursor: self.write(cursor, -math.inf, state, [],
                                                       analytics=analytics))

    def due(self, released: float) -> bool:
        """Whether the tracker after a group with watermark ``released`` is snapshotted."""
        return self._last is None or released - self._last >= self.policy.snapshot_interval_s

    def taking(self, released: float) -> None:
        """A snapshot at ``released`` is being taken (the next is due an interval later)."""
        self._last = released

    def write(self, cursor: sqlite3.Cursor, released: float, state: Any,
              boundary: Sequence[tuple[str, int]], rows_after: int = 0,
              analytics: Any = None) -> None:
        """Inside the group's transaction, after its rows: save a snapshot, prune old ones.

        Args:
            released: the watermark of the last group the state has seen, seconds.
            state: the matcher's ``get_state()`` then, or it as JSON text
                (:func:`state_text`, taken at once: a later update cannot change it).
            boundary: keys ``(camera, sequence)`` of the messages at ``released`` it has seen.
            rows_after: track rows the transaction wrote after that group (its later groups').
            analytics: the online analytics' state then (their events and counts until
                then are written before this call), or None.
        """
        (track_row,) = cursor.execute("SELECT COALESCE(MAX(row), 0) FROM tracks").fetchone()
        (event_row,) = cursor.execute("SELECT COALESCE(MAX(id), 0) FROM events").fetchone()
        cursor.execute(
            "INSERT OR REPLACE INTO snapshots "
            "(released, track_row, boundary, state, event_row, analytics) "
            "VALUES (?, ?, ?, ?, ?, ?)",
            (released, int(track_row) - rows_after,
             json.dumps([list(key) for key in boundary]),
             state if isinstance(state, str) else state_text(state), int(event_row),
             None if analytics is None else state_text(analytics)))
        # Keep the newest snapshot at or before the horizon too: every late message within
        # the horizon then has a snapshot before it.
        cursor.execute(
            "DELETE FROM snapshots WHERE released < "
            "(SELECT MAX(released) FROM snapshots WHERE released <= ?)",
            (released - self.policy.horizon_s,))
        cursor.execute(
            "DELETE FROM snapshots WHERE released NOT IN "
            "(SELECT released FROM snapshots ORDER BY released DESC LIMIT ?)",
            (self.policy.max_snapshots,))
        (oldest,) = cursor.execute("SELECT MIN(released) FROM snapshots").fetchone()
        prune_log(cursor, float(oldest))  # nothing re-tracks from before the oldest

    def forget_after(self, cursor: sqlite3.Cursor, released: float) -> None:
        """Delete the snapshots after ``released`` (re-tracking replaces them)."""
        cursor.execute("DELETE FROM snapshots WHERE released > ?", (released,))


def retrack(store: RuntimeStore, matcher: Any, camera_ids: Sequence[str],
            snapshots: Snapshots, tracker: str | None = None,
            analytics: Any = None) -> Retracked:
    """Track the late messages not looked at yet (see the module docstring).

    Args:
        store: the tracker process's store.
        matcher: the matcher; it is left in the re-tracked state (the one committed).
        camera_ids: the plane's cameras.
        snapshots: the process's snapshots.
        tracker: the service's claim on the store (nothing is committed without it).
        analytics: the plane's online analytics (they follow the correction), or None.

    Returns:
        The re-tracked windows and the counters committed.
    """
    seen = int(store.get_meta(SEEN_KEY, 0))
    late = store.query("SELECT rowid, timestamp FROM inbox WHERE status = ? AND rowid > ?",
                       (LATE, seen))
    if not late:
        return Retracked()
    newest_seen = max(rowid for rowid, _ in late)
    # A snapshot before inbox rows that retention deleted would re-track without them.
    deleted_until = store.get_meta(DELETED_KEY)
    if deleted_until is not None:
        store.write(lambda cursor: cursor.execute(
            "DELETE FROM snapshots WHERE released < ?", (float(deleted_until),)))
    (oldest,) = store.query("SELECT MIN(released) FROM snapshots")[0]
    trackable = {rowid: timestamp for rowid, timestamp in late
                 if oldest is not None and timestamp > oldest}
    counters = {"late_untracked": len(late) - len(trackable)}
    if not trackable:
        store.write(lambda cursor: _commit_seen(cursor, store, tracker, newest_seen, counters))
        return Retracked(counters=counters)
    released, track_row, boundary, state, event_row, counted = store.query(
        "SELECT released, track_row, boundary, state, event_row, analytics FROM snapshots "
        "WHERE released < ? ORDER BY released DESC LIMIT 1", (min(trackable.values()),))[0]
    released = float(released)
    entries = _entries_after(store, released, {tuple(key) for key in json.loads(boundary)},
                             set(trackable))
    matcher.set_state(json.loads(state))
    recount = analytics is not None and counted is not None
    if analytics is not None and not recount:
        counters["analytics_uncorrected"] = 1
    if recount:
        analytics.set_state(json.loads(counted), _counts_at(store, released))
        analytics.log_floor = math.nextafter(released, math.inf)
    events: dict[str, int] = {}

    def count(tracks: Tracks, timestamp: float) -> None:
        if recount:
            for event in analytics.update(tracks, timestamp):
                events[event.kind] = events.get(event.kind, 0) + 1

    orderer = Orderer(camera_ids, timeout_s=1e9)  # everything is here: released at once
    for entry in entries:
        orderer.add(entry, 0.0)
    windows: list[tuple[float, Tracks]] = []
    # After window index: (index, time, matcher state, keys at it, analytics writes until then)
    saved: list[tuple[int, float, Any, list[tuple[str, int]], Any]] = []
    snapshots.taking(released)
    fed: dict[float, list[tuple[str, int]]] = {}
    for timestamp, members in orderer.release(0.0, force=True):
        windows.append((timestamp, matcher.update(timestamp, [e.message() for e in members])))
        count(windows[-1][1], timestamp)
        for entry in members:
            fed.setdefault(entry.timestamp, []).append((entry.camera_id, entry.sequence))
        if snapshots.due(timestamp):
            snapshots.taking(timestamp)
            saved.append((len(windows) - 1, timestamp, state_text(matcher.get_state()),
                          list(fed.get(timestamp, [])),
                          analytics.take_writes() if recount else None))
    watermark = store.released_timestamp()
    if watermark is not None and windows and watermark > windows[-1][0]:
        # As far as the undisturbed run had come: everything up to it has been delivered.
        final = matcher.update(watermark, [])
        count(final, watermark)
        last_time, last_tracks = windows[-1]
        windows[-1] = (last_time, Tracks.concatenate([last_tracks, final]))
    counters.update({"retracks": 1, "retracked": len(entries), "late_tracked": len(trackable),
                     "processed": len(trackable)})
    state_after = matcher.get_state()
    rest = None
    if recount:
        rest = analytics.take_writes()
        analytics.log_floor = -math.inf

    def commit(cursor: sqlite3.Cursor) -> None:
        if tracker is not None:
            check_tracker(cursor, store.path, tracker)
        if recount:
            taken_back = roll_back(cursor, released, int(event_row))
            keep_published(taken_back, [item[4] for item in saved] + [rest])
        cursor.execute("DELETE FROM tracks WHERE row > ?", (int(track_row),))
        # ``tracks`` counts the rows stored: the re-tracked ones replace those deleted.
        counters["tracks"] = sum(len(tracks) for _, tracks in windows) - cursor.rowcount
        snapshots.forget_after(cursor, released)
        pending = iter(saved)
        upcoming = next(pending, None)
        for index, (_, tracks) in enumerate(windows):
            cursor.executemany(INSERT_TRACKS, track_rows(tracks))
            if upcoming is not None and upcoming[0] == index:
                if upcoming[4] is not None:
                    upcoming[4](cursor)
                snapshots.write(cursor, upcoming[1], upcoming[2], upcoming[3],
                                analytics=None if upcoming[4] is None else upcoming[4].state)
                upcoming = next(pending, None)
        if rest is not None:
            rest(cursor)
        cursor.executemany("UPDATE inbox SET status = ? WHERE rowid = ?",
                           [(PROCESSED, rowid) for rowid in trackable])
        set_matcher_state(cursor, state_after)
        _commit_seen(cursor, store, None, newest_seen, counters)

    store.write(commit)
    return Retracked(windows, released, counters, events)


def _counts_at(store: RuntimeStore, released: float) -> dict[tuple[str, str, str], float]:
    """The ``counts`` as they were at a snapshot at ``released``: today's minus the
    increments logged after it (the running totals of the events start from these)."""
    counts = read_counts(store)
    for key, value in store.query(
            "SELECT key, SUM(value) FROM count_log WHERE tbl = 'counts' AND released > ? "
            "GROUP BY key", (released,)):
        place, measure, klass = json.loads(key)
        counts[(place, measure, klass)] = counts.get((place, measure, klass), 0.0) - value
    return counts


def state_text(state: Any) -> str:
    """A matcher state as the JSON text a snapshot stores (numpy values as plain ones)."""
    return json.dumps(state, default=_plain)


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in a matcher snapshot")


def _entries_after(store: RuntimeStore, released: float, boundary: set[tuple[str, int]],
                   late_rows: set[int]) -> list[InboxEntry]:
    """The inbox messages a snapshot at ``released`` has not seen: processed ones after it
    (at it: those not in its ``boundary``) and the late ones being tracked."""
    rows = store.query(
        "SELECT rowid, status, camera_id, sequence, timestamp, frame, body FROM inbox "
        "WHERE status IN (?, ?) AND timestamp >= ? ORDER BY timestamp, camera_id, sequence",
        (PROCESSED, LATE, released))
    return [
        InboxEntry(camera, int(sequence), float(timestamp), int(frame), body)
        for rowid, status, camera, sequence, timestamp, frame, body in rows
        if (status == PROCESSED or rowid in late_rows)
        and not (timestamp == released and (camera, sequence) in boundary)
    ]


def _create_table(cursor: sqlite3.Cursor) -> None:
    cursor.execute(SNAPSHOTS_SCHEMA)
    columns = {row[1] for row in cursor.execute("PRAGMA table_info(snapshots)")}
    for column, kind in (("event_row", "INTEGER"), ("analytics", "TEXT")):
        if column not in columns:  # a database written before the analytics were kept
            cursor.execute(f"ALTER TABLE snapshots ADD COLUMN {column} {kind}")


def _commit_seen(cursor: sqlite3.Cursor, store: RuntimeStore, tracker: str | None,
                 newest_seen: int, counters: dict[str, int]) -> None:
    if tracker is not None:
        check_tracker(cursor, store.path, tracker)
    set_meta_value(cursor, SEEN_KEY, newest_seen)
    add_counter_values(cursor, counters)
