"""The online analytics' tables in the matcher's SQLite file: event outbox and counters.

Tables (created with the store's own, see :mod:`cblrs.runtime.matcher.store_schema`):

* ``events`` — every final analytics event (``line_crossed``, ``zone_entered``,
  ``zone_left``) in the order the engine emitted them; ``id`` is the plane's event sequence,
  ``key`` the event's natural identity (kind, place, track, time: the same event computed
  again, e.g. by a matcher rebuilding the plane, has the same key), ``body`` the event as
  published (without ``id``), ``published`` 1 once the broker acknowledged it. It is the
  outbox: a restarted matcher publishes what is not yet marked.
* ``counts`` — persistent counters per place, measure and class name: ``positive`` /
  ``negative`` crossings of a line; ``entries``, ``appeared``, ``exits``, ``visits``,
  ``dwell_s`` (sum), ``complete_visits`` and ``complete_dwell_s`` (visits that entered and
  exited), ``od_unpaired`` of a zone. They never shrink: retention leaves them alone.
* ``count_bins`` — the same per time bin (``start``, epoch seconds; with a site ``timezone``
  the local bin's start, e.g. local hh:00 for hours; bins of the analytics'
  ``interval_s``): line directions, zone ``entries`` / ``exits`` and ``occupancy_s``
  (person-seconds), for charts and Grafana.
* ``od`` — origin-destination counts between zones.
* ``count_log`` — with re-tracking on (:mod:`cblrs.runtime.matcher.retrack`): every
  increment of ``counts``, ``count_bins``, ``od`` and the analytics' counters with the time
  of the tracker group that made it, kept as long as the snapshots, so a re-tracking from a
  snapshot takes back what was counted after it (:func:`roll_back`) and counts the
  corrected tracks instead.

Every write of one tracker batch goes into the transaction that stores the batch's track
rows and the engine's state (:meth:`RuntimeStore.commit_group`'s ``also``), so after a
crash the file holds a batch's tracks, events and counts together or none of them.
"""

from __future__ import annotations

import json
import sqlite3
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from cblrs.analytics.config import AnalyticsConfig
from cblrs.places import LineRule, Places, line_rule_text

ANALYTICS_SCHEMA = """
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    timestamp REAL NOT NULL,
    kind TEXT NOT NULL,
    place TEXT NOT NULL,
    track_id INTEGER NOT NULL,
    key TEXT NOT NULL UNIQUE,
    body TEXT NOT NULL,
    published INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS events_unpublished ON events (id) WHERE published = 0;
CREATE TABLE IF NOT EXISTS counts (
    place TEXT NOT NULL,
    measure TEXT NOT NULL,
    class TEXT NOT NULL,
    value REAL NOT NULL,
    PRIMARY KEY (place, measure, class)
);
CREATE TABLE IF NOT EXISTS count_bins (
    start REAL NOT NULL,
    place TEXT NOT NULL,
    measure TEXT NOT NULL,
    class TEXT NOT NULL,
    value REAL NOT NULL,
    PRIMARY KEY (start, place, measure, class)
);
CREATE TABLE IF NOT EXISTS od (
    origin TEXT NOT NULL,
    destination TEXT NOT NULL,
    value INTEGER NOT NULL,
    PRIMARY KEY (origin, destination)
);
CREATE TABLE IF NOT EXISTS count_log (
    released REAL NOT NULL,
    tbl TEXT NOT NULL,
    key TEXT NOT NULL,
    value REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS count_log_released ON count_log (released);
"""

STATE_KEY = "analytics_state"
"""The ``meta`` key of the engine's state."""

CountKey = tuple[str, str, str]
"""``(place, measure, class name)``."""
BinKey = tuple[float, str, str, str]
"""``(bin start seconds, place, measure, class name)``."""


@dataclass
class AnalyticsWrites:
    """What one tracker batch adds to the analytics tables (see the module docstring).

    Attributes:
        events: ``(timestamp, kind, place, track_id, key, body)`` in emission order.
        counts: increments of ``counts``.
        bins: increments of ``count_bins``.
        od: increments of ``od``.
        counters: increments of the store's ``counters`` (rows, late rows).
        state: the engine's state after the batch (``meta``), or None to leave it.
        log: ``(group time, table, key, increment)`` for ``count_log`` (``table``: counts,
            bins, od, or counters: the analytics' own, e.g. ``analytics_rows``).
        published: keys of events to insert as already published (a re-tracking found
            again an event that was published before it).
    """

    events: list[tuple[float, str, str, int, str, str]] = field(default_factory=list)
    counts: dict[CountKey, float] = field(default_factory=lambda: defaultdict(float))
    bins: dict[BinKey, float] = field(default_factory=lambda: defaultdict(float))
    od: dict[tuple[str, str], int] = field(default_factory=lambda: defaultdict(int))
    counters: dict[str, int] = field(default_factory=dict)
    state: dict[str, Any] | None = None
    log: list[tuple[float, str, tuple, float]] = field(default_factory=list)
    published: set[str] = field(default_factory=set)

    def __call__(self, cursor: sqlite3.Cursor) -> None:
        """Write everything with ``cursor`` (inside the caller's transaction)."""
        write_analytics(cursor, self)


def write_analytics(cursor: sqlite3.Cursor, writes: AnalyticsWrites) -> None:
    """Apply :class:`AnalyticsWrites` with ``cursor`` (inside the caller's transaction)."""
    cursor.executemany(
        "INSERT OR IGNORE INTO events (timestamp, kind, place, track_id, key, body, published) "
        "VALUES (?, ?, ?, ?, ?, ?, ?)",
        [(*row, int(row[4] in writes.published)) for row in writes.events],
    )
    cursor.executemany(
        "INSERT INTO count_log (released, tbl, key, value) VALUES (?, ?, ?, ?)",
        [(released, table, json.dumps(list(key)), value)
         for released, table, key, value in writes.log],
    )
    cursor.executemany(
        "INSERT INTO counts (place, measure, class, value) VALUES (?, ?, ?, ?) "
        "ON CONFLICT(place, measure, class) DO UPDATE SET value = value + excluded.value",
        [(*key, value) for key, value in writes.counts.items() if value],
    )
    cursor.executemany(
        "INSERT INTO count_bins (start, place, measure, class, value) VALUES (?, ?, ?, ?, ?) "
        "ON CONFLICT(start, place, measure, class) DO UPDATE SET value = value + excluded.value",
        [(*key, value) for key, value in writes.bins.items() if value],
    )
    cursor.executemany(
        "INSERT INTO od (origin, destination, value) VALUES (?, ?, ?) "
        "ON CONFLICT(origin, destination) DO UPDATE SET value = value + excluded.value",
        [(*key, value) for key, value in writes.od.items() if value],
    )
    cursor.executemany(
        "INSERT INTO counters (name, value) VALUES (?, ?) "
        "ON CONFLICT(name) DO UPDATE SET value = value + excluded.value",
        [(name, int(value)) for name, value in writes.counters.items() if value],
    )
    if writes.state is not None:
        cursor.execute(
            "INSERT INTO meta (key, value) VALUES (?, ?) "
            "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
            (STATE_KEY, json.dumps(writes.state)),
        )


_ROLLBACK_SQL = {
    "counts": "UPDATE counts SET value = value - ? WHERE place = ? AND measure = ? AND class = ?",
    "bins": "UPDATE count_bins SET value = value - ? "
            "WHERE start = ? AND place = ? AND measure = ? AND class = ?",
    "od": "UPDATE od SET value = value - ? WHERE origin = ? AND destination = ?",
    "counters": "UPDATE counters SET value = value - CAST(? AS INTEGER) WHERE name = ?",
}


@dataclass
class RolledBack:
    """What :func:`roll_back` took back.

    Attributes:
        counts: the ``counts`` increments taken back (to restore the running totals).
        events: ``(key, body)`` of the events deleted, in id order.
        published: keys among them that had been published.
    """

    counts: dict[CountKey, float] = field(default_factory=lambda: defaultdict(float))
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    published: set[str] = field(default_factory=set)


def roll_back(cursor: sqlite3.Cursor, after: float, event_id: int,
              after_row: int | None = None) -> RolledBack:
    """Take back everything the analytics counted after a snapshot (inside the
    re-tracking's transaction): the logged increments of groups after ``after`` (with
    ``after_row``: the increments logged after that ``count_log`` row, whatever their time;
    the linker's snapshots) and the events after id ``event_id``."""
    rolled = RolledBack()
    increments: dict[tuple[str, str], float] = defaultdict(float)
    where, bound = ("released > ?", after) if after_row is None else ("rowid > ?", after_row)
    for table, key, value in cursor.execute(
            f"SELECT tbl, key, value FROM count_log WHERE {where}", (bound,)).fetchall():
        increments[(table, key)] += value
    for (table, key), value in increments.items():
        parts = tuple(json.loads(key))
        cursor.execute(_ROLLBACK_SQL[table], (value, *parts))
        if table == "counts":
            rolled.counts[parts] += value  # type: ignore[index]
    cursor.execute(f"DELETE FROM count_log WHERE {where}", (bound,))
    for key, body, published in cursor.execute(
            "SELECT key, body, published FROM events WHERE id > ? ORDER BY id",
            (int(event_id),)).fetchall():
        rolled.events.append((key, json.loads(body)))
        if published:
            rolled.published.add(key)
    cursor.execute("DELETE FROM events WHERE id > ?", (int(event_id),))
    return rolled


def keep_published(taken_back: RolledBack, recounted: Sequence[Any]) -> None:
    """An event counted again that was published before keeps its published mark (it is not
    published twice); a published event not counted again is taken back by an
    ``event_retracted`` event, added to the last writes."""
    found = {row[4] for writes in recounted if writes is not None for row in writes.events}
    for writes in recounted:
        if writes is not None:
            writes.published = taken_back.published
    last = next(writes for writes in reversed(recounted) if writes is not None)
    for key, body in taken_back.events:
        if body.get("kind") == "event_retracted":
            if body.get("retracted") not in found:  # an earlier correction's: it stands
                last.events.append((float(body.get("timestamp") or 0.0), "event_retracted",
                                    str(body.get("place", "")), int(body.get("track") or 0),
                                    key, json.dumps(body)))
        elif key in taken_back.published and key not in found:
            retraction = {"kind": "event_retracted", "timestamp": body.get("timestamp"),
                          "track": body.get("track"), "place": body.get("place"),
                          "retracted": key, "retracted_kind": body.get("kind")}
            retraction_key = f"retracted/{key}"
            retraction["key"] = retraction_key
            last.events.append((float(body.get("timestamp") or 0.0), "event_retracted",
                                str(body.get("place", "")), int(body.get("track") or 0),
                                retraction_key, json.dumps(retraction)))


def prune_log(cursor: sqlite3.Cursor, until: float) -> None:
    """Forget the logged increments at or before ``until`` (no snapshot before them)."""
    cursor.execute("DELETE FROM count_log WHERE released <= ?", (until,))


# ---------------------------------------------------------------------------- reads


def read_state(store: Any) -> dict[str, Any] | None:
    """The engine state a store holds (None before the first batch)."""
    rows = store.query("SELECT value FROM meta WHERE key = ?", (STATE_KEY,))
    return json.loads(rows[0][0]) if rows else None


def line_rules(store: Any) -> dict[str, str]:
    """What counted as a crossing of each line (:func:`cblrs.places.line_rule_text`), from
    the settings and places of the store's saved state; empty before the first batch."""
    state = read_state(store)
    engine = (state or {}).get("engine") or {}
    if "places" not in engine or "config" not in engine:
        return {}
    places = Places.from_dict(engine["places"])
    config = AnalyticsConfig.from_dict({"line_rule": LineRule.HYSTERESIS.value,
                                        **engine["config"]})
    return {line.name: line_rule_text(rule, band)
            for line, (rule, band) in zip(places.lines, config.line_rules(places), strict=True)}


def read_counts(store: Any) -> dict[CountKey, float]:
    """Every counter of ``counts``: ``{(place, measure, class): value}``."""
    return {
        (place, measure, klass): float(value)
        for place, measure, klass, value in store.query(
            "SELECT place, measure, class, value FROM counts"
        )
    }


def read_od(store: Any) -> dict[tuple[str, str], int]:
    """Origin-destination counts stored by the online analytics: {(origin, destination): n}."""
    return {
        (origin, destination): int(value)
        for origin, destination, value in store.query("SELECT origin, destination, value FROM od")
    }


def read_bins(store: Any) -> dict[BinKey, float]:
    """Binned counts stored by the online analytics: {(start, place, measure, class): value}."""
    return {
        (float(start), place, measure, klass): float(value)
        for start, place, measure, klass, value in store.query(
            "SELECT start, place, measure, class, value FROM count_bins"
        )
    }


def count_summary(counts: Mapping[CountKey, float]) -> dict[str, dict[str, dict[str, float]]]:
    """Counters summed over classes: ``{"lines": {line: {direction: n}}, "zones": {zone:
    {measure: value}}}`` plus each zone's ``mean_dwell_s``."""
    lines: dict[str, dict[str, float]] = {}
    zones: dict[str, dict[str, float]] = {}
    for (place, measure, _), value in counts.items():
        table = lines if measure in ("positive", "negative") else zones
        row = table.setdefault(place, {})
        row[measure] = row.get(measure, 0.0) + value
    for row in zones.values():
        visits = row.get("visits", 0.0)
        row["mean_dwell_s"] = row.get("dwell_s", 0.0) / visits if visits else 0.0
    return {"lines": lines, "zones": zones}


@dataclass(frozen=True)
class StoredEvent:
    """An ``events`` row: ``id``, the event ``body`` (a dict) and whether it was published."""

    id: int
    body: dict[str, Any]
    published: bool


def read_events(
    store: Any,
    *,
    after_id: int = 0,
    unpublished: bool = False,
    until_timestamp: float | None = None,
    limit: int | None = None,
) -> list[StoredEvent]:
    """Events in id order (emission order).

    Args:
        after_id: only ids above this.
        unpublished: only those not yet acknowledged by the broker.
        until_timestamp: only events at or before this time, seconds.
        limit: at most this many.
    """
    sql = "SELECT id, body, published FROM events WHERE id > ?"
    parameters: list[Any] = [int(after_id)]
    if unpublished:
        sql += " AND published = 0"
    if until_timestamp is not None:
        sql += " AND timestamp <= ?"
        parameters.append(float(until_timestamp))
    sql += " ORDER BY id"
    if limit is not None:
        sql += f" LIMIT {int(limit)}"
    return [
        StoredEvent(int(identifier), json.loads(body), bool(published))
        for identifier, body, published in store.query(sql, tuple(parameters))
    ]


def mark_published(store: Any, identifiers: Iterable[int]) -> None:
    """Mark events as acknowledged by the broker (one transaction)."""
    rows = [(int(identifier),) for identifier in identifiers]
    if rows:
        store.write(
            lambda cursor: cursor.executemany("UPDATE events SET published = 1 WHERE id = ?", rows)
        )


RETAINED_EVENTS = ("events", "timestamp", "published = 1")
"""Retention of the outbox: events may go once published (``RetainedTable`` arguments)."""
RETAINED_BINS = ("count_bins", "start", "1")
"""Retention of the binned counts (the totals in ``counts`` are kept for ever)."""
