"""The linker's durable state in one SQLite file (WAL mode), like the matcher's store.

Tables:

* ``updates`` — every plane track update the linker took, unique by ``(plane, timestamp)``
  (the update's time: a matcher publishes one update per timestamp group, and a matcher that
  rebuilt its plane on another host publishes the same ones again): the de-duplication set,
  across restarts;
* ``tracks`` — the global rows: time, frame, global id, world x/y, class, and the plane and
  plane track they came from;
* ``handovers`` — every hand-over decided (global id, time, from plane/track, to
  plane/track, overlap or portal, score);
* ``meta`` — the linker's state (:meth:`~cblrs.linking.PlaneLinker.get_state`), each plane's
  clock, the site it links (a file linked for another site is refused);
* ``counters`` — updates, rows, duplicates, rejected by reason, late rows, ...;
* ``inputs`` — every plane row the linker took, for ``SNAPSHOT_HORIZON_S`` behind its clock,
  and ``snapshots`` — the linker's and the analytics' states every ``SNAPSHOT_INTERVAL_S`` of
  its clock, with the last global row, hand-over, event and count increment then; and
  ``corrections`` — the keys ``(plane, update time, corrected_from)`` of the matchers'
  corrections taken: a plane's correction (late messages re-tracked,
  :mod:`cblrs.runtime.matcher.retrack`) replaces that plane's inputs after its time, and the
  linker goes back to the newest snapshot at or before it and links again
  (:mod:`cblrs.runtime.outputs.linker_service`);
* ``events``, ``counts``, ``count_bins``, ``od`` — the site's analytics (the matcher's
  tables, :mod:`cblrs.runtime.outputs.analytics_store`), counted on the global rows.

One batch of updates is one transaction (update keys, global rows, hand-overs, the linker's
and the analytics' states, counters), and the service acknowledges the batch's deliveries
only after it: a linker killed at any moment resumes from a state that matches its rows, and
the updates it had not committed come again and are taken once.

The file holds people's positions: created with mode 0600, a second linker on it is refused
(:meth:`LinkerStore.hold`), a file deleted or replaced under a running linker fails the next
commit.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sqlite3
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.linking.linker import Handover, LinkedRows
from cblrs.runtime.outputs.analytics_store import (
    ANALYTICS_SCHEMA,
    AnalyticsWrites,
    keep_published,
    read_counts,
    roll_back,
    write_analytics,
)

SQLITE_HEADER = b"SQLite format 3\x00"
_OWN_TABLES = frozenset({"updates", "handovers"})

_SCHEMA = """
CREATE TABLE IF NOT EXISTS updates (
    plane INTEGER NOT NULL,
    timestamp REAL NOT NULL,
    received_at REAL NOT NULL,
    rows INTEGER NOT NULL,
    PRIMARY KEY (plane, timestamp)
);
CREATE TABLE IF NOT EXISTS tracks (
    row INTEGER PRIMARY KEY AUTOINCREMENT,
    timestamp REAL NOT NULL,
    frame INTEGER NOT NULL,
    track_id INTEGER NOT NULL,
    x REAL NOT NULL,
    y REAL NOT NULL,
    class_id INTEGER NOT NULL,
    plane INTEGER NOT NULL,
    plane_track INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS handovers (
    global_id INTEGER NOT NULL,
    timestamp REAL NOT NULL,
    from_plane INTEGER NOT NULL,
    from_track INTEGER NOT NULL,
    to_plane INTEGER NOT NULL,
    to_track INTEGER NOT NULL,
    kind TEXT NOT NULL,
    score REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS inputs (
    plane INTEGER NOT NULL,
    timestamp REAL NOT NULL,
    frame INTEGER NOT NULL,
    track_id INTEGER NOT NULL,
    x REAL NOT NULL,
    y REAL NOT NULL,
    class_id INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS inputs_time ON inputs (timestamp);
CREATE TABLE IF NOT EXISTS snapshots (
    clock REAL PRIMARY KEY,
    emitted_until REAL NOT NULL,
    track_row INTEGER NOT NULL,
    handover_row INTEGER NOT NULL,
    event_row INTEGER NOT NULL,
    log_row INTEGER NOT NULL,
    state TEXT NOT NULL,
    analytics TEXT
);
CREATE TABLE IF NOT EXISTS corrections (
    plane INTEGER NOT NULL,
    timestamp REAL NOT NULL,
    corrected_from REAL NOT NULL,
    PRIMARY KEY (plane, timestamp, corrected_from)
);
""" + ANALYTICS_SCHEMA

SNAPSHOT_INTERVAL_S = 5.0
"""Seconds of the linker's clock between two snapshots."""
SNAPSHOT_HORIZON_S = 600.0
"""Snapshots (and inputs) are kept this long behind the newest: a correction from before the
oldest one is not linked again (the matchers' default ``--late-horizon`` is as long)."""


class LinkerStoreError(CblrsError):
    """The linker's database cannot be opened, is held, or belongs to another site."""


@dataclass
class LinkerBatch:
    """What one batch of plane updates writes (see the module docstring).

    Attributes:
        updates: ``(plane, timestamp, received_at, rows)`` of the updates taken.
        rows: the global rows that became final.
        handovers: the hand-overs decided.
        state: the linker's state after the batch.
        clocks: each plane's clock (the newest update time taken), for the next start.
        lags: each plane's largest lag between an update's time and its earliest row.
        counters: increments of the counters.
        analytics: the site analytics' writes (None without analytics).
        inputs: in order, ``("add", plane, rows)`` (rows taken), ``("cut", plane, time)`` (a
            correction begins: the plane's inputs after ``time`` are replaced) and
            ``("fix", plane, rows)`` (a correction's rows).
        corrections: keys ``(plane, update time, corrected_from)`` of the corrections taken.
        rewound: the snapshot the linker went back to (:meth:`LinkerStore.snapshot_at`):
            the global rows, hand-overs, events and counts after it are taken back first.
        snapshot: a snapshot to take after the batch (``clock``, ``emitted_until``, ``state``,
            ``analytics``).
        correcting: each plane's correction under way (``[corrected_from, update time, the
            plane's clock when it began]``; caught up once its update time reaches that).
    """

    updates: list[tuple[int, float, float, int]] = field(default_factory=list)
    rows: LinkedRows = field(default_factory=LinkedRows.empty)
    handovers: list[Handover] = field(default_factory=list)
    state: dict[str, Any] | None = None
    clocks: dict[int, float] = field(default_factory=dict)
    lags: dict[int, float] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=dict)
    analytics: AnalyticsWrites | None = None
    inputs: list[tuple[str, int, Any]] = field(default_factory=list)
    corrections: list[tuple[int, float, float]] = field(default_factory=list)
    rewound: Snapshot | None = None
    snapshot: dict[str, Any] | None = None
    correcting: dict[int, list[float]] | None = None


@dataclass(frozen=True)
class Snapshot:
    """A snapshot the linker can go back to (see the module docstring)."""

    clock: float
    emitted_until: float
    track_row: int
    handover_row: int
    event_row: int
    log_row: int
    state: dict[str, Any]
    analytics: dict[str, Any] | None


class LinkerStore:
    """The SQLite file of one site's linker.

    Args:
        path: the database file (created with its tables when missing; its folder must exist).
        read_only: open for reading only (the file must exist).

    Raises:
        LinkerStoreError: the file cannot be a linker database (see the module docstring).
    """

    def __init__(self, path: str | Path, read_only: bool = False):
        self.path = Path(path)
        self._lock = threading.RLock()
        self._holder: Any = None
        _check_file(self.path, read_only)
        try:
            if read_only:
                self._connection = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True,
                                                   check_same_thread=False)
                self._check_tables()
            else:
                if not self.path.exists():
                    os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
                self._connection = sqlite3.connect(str(self.path), check_same_thread=False,
                                                   isolation_level=None)
                self._check_tables()
                self._connection.execute("PRAGMA journal_mode=WAL")
                self._connection.execute("PRAGMA synchronous=NORMAL")
                self._connection.executescript(_SCHEMA)
                for name in (self.path.name, self.path.name + "-wal", self.path.name + "-shm"):
                    try:
                        os.chmod(self.path.with_name(name), 0o600)
                    except OSError:
                        pass
            self._connection.execute("PRAGMA busy_timeout=5000")
        except sqlite3.DatabaseError as error:
            raise LinkerStoreError(f"{self.path} is not a usable SQLite database: {error}.") \
                from None
        self._identity = _identity(self.path)

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        with self._lock:
            self._connection.close()
            if self._holder is not None:
                self._holder.close()
                self._holder = None

    def __enter__(self) -> LinkerStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def hold(self) -> None:
        """Hold the file for one linker until :meth:`close`.

        Raises:
            LinkerStoreError: another linker (still running) holds it.
        """
        if self._holder is not None:
            return
        path = self.path.with_name(self.path.name + "-linker.lock")
        handle = os.fdopen(os.open(path, os.O_RDWR | os.O_CREAT, 0o600), "r+")
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            owner = handle.read().strip() or "another process"
            handle.close()
            raise LinkerStoreError(f"{self.path} is in use by another linker ({owner}); stop "
                                   "it first or use another --db.") from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        handle.flush()
        self._holder = handle

    def bind(self, site: Mapping[str, Any]) -> None:
        """Record what the file links (the site's planes and links) or check it is the same.

        Raises:
            LinkerStoreError: the file links another site.
        """
        wanted = json.loads(json.dumps(dict(site)))
        stored = self.get_meta("site")
        if stored is None:
            self.set_meta("site", wanted)
        elif stored != wanted:
            different = sorted(key for key in set(stored) | set(wanted)
                               if stored.get(key) != wanted.get(key))
            raise LinkerStoreError(
                f"{self.path} links another site (its {different[0]} differ); use another "
                "--db, or the site file it was linked with."
            )

    def _check_tables(self) -> None:
        names = {name for (name,) in self._connection.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")}
        if names and not names & _OWN_TABLES:
            raise LinkerStoreError(
                f"{self.path} is not a cblrs linker database (tables "
                f"{', '.join(sorted(names)[:5])}); choose another --db."
            )

    def _check_identity(self) -> None:
        try:
            current = _identity(self.path)
        except OSError:
            current = None
        if current != self._identity:
            raise LinkerStoreError(
                f"the database {self.path} was deleted or replaced while the linker was "
                "running; nothing more is acknowledged."
            )

    # ------------------------------------------------------------------ writes
    def set_meta(self, key: str, value: Any) -> None:
        with self._lock:
            self._connection.execute(
                "INSERT INTO meta (key, value) VALUES (?, ?) "
                "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (key, json.dumps(value)))

    def commit(self, batch: LinkerBatch) -> None:
        """Write one batch in one transaction (see :class:`LinkerBatch`).

        Raises:
            LinkerStoreError: the file was deleted or replaced.
        """
        rows = batch.rows
        tracks = rows.tracks
        track_rows = list(zip(
            tracks.timestamp.tolist(), tracks.frame.tolist(), tracks.track_id.tolist(),
            tracks.world_xy[:, 0].tolist(), tracks.world_xy[:, 1].tolist(),
            tracks.class_id.tolist(), rows.plane_id.tolist(), rows.local_track_id.tolist(),
            strict=True))
        with self._lock:
            self._check_identity()
            cursor = self._connection.cursor()
            cursor.execute("BEGIN IMMEDIATE")
            try:
                if batch.rewound is not None:  # first: what was linked after the snapshot
                    _take_back(cursor, batch)
                cursor.executemany("INSERT OR IGNORE INTO updates (plane, timestamp, "
                                   "received_at, rows) VALUES (?, ?, ?, ?)", batch.updates)
                cursor.executemany("INSERT INTO tracks (timestamp, frame, track_id, x, y, "
                                   "class_id, plane, plane_track) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                                   track_rows)
                cursor.executemany(
                    "INSERT INTO handovers VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    [(item.global_id, item.timestamp, item.from_plane, item.from_track,
                      item.to_plane, item.to_track, item.kind, item.score)
                     for item in batch.handovers])
                if batch.state is not None:
                    _set_meta(cursor, "linker_state", batch.state)
                if batch.clocks:
                    _set_meta(cursor, "plane_clocks",
                              {str(plane): value for plane, value in batch.clocks.items()})
                if batch.lags:
                    _set_meta(cursor, "plane_lags",
                              {str(plane): value for plane, value in batch.lags.items()})
                cursor.executemany(
                    "INSERT INTO counters (name, value) VALUES (?, ?) "
                    "ON CONFLICT(name) DO UPDATE SET value = value + excluded.value",
                    [(name, int(value)) for name, value in batch.counters.items() if value])
                _write_inputs(cursor, batch)
                if batch.analytics is not None:
                    write_analytics(cursor, batch.analytics)
                if batch.snapshot is not None:
                    _write_snapshot(cursor, batch.snapshot)
                cursor.execute("COMMIT")
            except BaseException:
                cursor.execute("ROLLBACK")
                raise
            self._check_identity()

    def write(self, writes: Any) -> Any:
        """Run ``writes(cursor)`` in one write transaction of its own (the event outbox marks
        what the broker acknowledged with it)."""
        with self._lock:
            self._check_identity()
            cursor = self._connection.cursor()
            cursor.execute("BEGIN IMMEDIATE")
            try:
                result = writes(cursor)
                cursor.execute("COMMIT")
            except BaseException:
                cursor.execute("ROLLBACK")
                raise
            return result

    # ------------------------------------------------------------------ reads
    def query(self, sql: str, parameters: tuple = ()) -> list[tuple]:
        """The rows of one read statement."""
        with self._lock:
            return self._connection.execute(sql, parameters).fetchall()

    def get_meta(self, key: str, default: Any = None) -> Any:
        rows = self.query("SELECT value FROM meta WHERE key = ?", (key,))
        return default if not rows else json.loads(rows[0][0])

    def linker_state(self) -> dict[str, Any] | None:
        """The linker's state after the last batch (None before the first)."""
        return self.get_meta("linker_state")

    def plane_clocks(self) -> dict[int, float]:
        """Each plane's newest update time taken."""
        return {int(plane): float(value)
                for plane, value in (self.get_meta("plane_clocks") or {}).items()}

    def plane_lags(self) -> dict[int, float]:
        """Each plane's largest lag between an update's time and its earliest row."""
        return {int(plane): float(value)
                for plane, value in (self.get_meta("plane_lags") or {}).items()}

    def seen(self, keys: Iterable[tuple[int, float]]) -> set[tuple[int, float]]:
        """Which of ``(plane, timestamp)`` update keys were taken already."""
        found = set()
        for plane, timestamp in keys:
            if self.query("SELECT 1 FROM updates WHERE plane = ? AND timestamp = ?",
                          (int(plane), float(timestamp))):
                found.add((int(plane), float(timestamp)))
        return found

    def counters(self) -> dict[str, int]:
        return {name: int(value) for name, value in
                sorted(self.query("SELECT name, value FROM counters"))}

    def rows(self) -> LinkedRows:
        """Every global row, in the order it became final."""
        rows = self.query("SELECT timestamp, frame, track_id, x, y, class_id, plane, "
                          "plane_track FROM tracks ORDER BY row")
        if not rows:
            return LinkedRows.empty()
        columns = list(zip(*rows, strict=True))
        return LinkedRows(
            tracks=Tracks(frame=np.array(columns[1], np.int64),
                          timestamp=np.array(columns[0], np.float64),
                          track_id=np.array(columns[2], np.int64),
                          world_xy=np.column_stack([columns[3], columns[4]]).astype(np.float64),
                          class_id=np.array(columns[5], np.int64)),
            plane_id=np.array(columns[6], np.int64),
            local_track_id=np.array(columns[7], np.int64),
        )

    def snapshot_at(self, time: float) -> Snapshot | None:
        """The newest snapshot at or before ``time`` (None: none is that old)."""
        rows = self.query(
            "SELECT clock, emitted_until, track_row, handover_row, event_row, log_row, state, "
            "analytics FROM snapshots WHERE clock <= ? ORDER BY clock DESC LIMIT 1", (time,))
        if not rows:
            return None
        clock, emitted, track_row, handover_row, event_row, log_row, state, counted = rows[0]
        return Snapshot(float(clock), float(emitted), int(track_row), int(handover_row),
                        int(event_row), int(log_row), json.loads(state),
                        None if counted is None else json.loads(counted))

    def has_snapshots(self) -> bool:
        return bool(self.query("SELECT 1 FROM snapshots LIMIT 1"))

    def inputs_after(self, time: float) -> dict[int, Tracks]:
        """Each plane's inputs after ``time``, in time order."""
        planes: dict[int, list[tuple]] = {}
        for row in self.query("SELECT plane, timestamp, frame, track_id, x, y, class_id FROM "
                              "inputs WHERE timestamp > ? ORDER BY rowid", (time,)):
            planes.setdefault(int(row[0]), []).append(row[1:])
        result = {}
        for plane, rows in planes.items():
            columns = list(zip(*rows, strict=True))
            tracks = Tracks(frame=np.array(columns[1], np.int64),
                            timestamp=np.array(columns[0], np.float64),
                            track_id=np.array(columns[2], np.int64),
                            world_xy=np.column_stack([columns[3], columns[4]]).astype(np.float64),
                            class_id=np.array(columns[5], np.int64))
            result[plane] = tracks[np.argsort(tracks.timestamp, kind="stable")]
        return result

    def counts_at(self, log_row: int) -> dict[tuple[str, str, str], float]:
        """The ``counts`` as they were when the count log ended at ``log_row``."""
        counts = read_counts(self)
        for key, value in self.query(
                "SELECT key, SUM(value) FROM count_log WHERE tbl = 'counts' AND rowid > ? "
                "GROUP BY key", (log_row,)):
            place, measure, klass = json.loads(key)
            counts[(place, measure, klass)] = counts.get((place, measure, klass), 0.0) - value
        return counts

    def seen_corrections(self, keys: Iterable[tuple[int, float, float]]
                         ) -> set[tuple[int, float, float]]:
        """Which correction keys were taken already."""
        return {key for key in keys if self.query(
            "SELECT 1 FROM corrections WHERE plane = ? AND timestamp = ? AND corrected_from = ?",
            key)}

    def handovers(self) -> list[Handover]:
        """Every hand-over, in the order decided."""
        return [Handover(int(g), float(t), int(fp), int(ft), int(tp), int(tt), str(kind),
                         float(score))
                for g, t, fp, ft, tp, tt, kind, score in self.query(
                    "SELECT * FROM handovers ORDER BY rowid")]


def _take_back(cursor: sqlite3.Cursor, batch: LinkerBatch) -> None:
    """Before a batch linked again from a snapshot: delete what was linked after it."""
    back = batch.rewound
    assert back is not None
    cursor.execute("DELETE FROM tracks WHERE row > ?", (back.track_row,))
    deleted = cursor.rowcount
    batch.counters["rows_out"] = batch.counters.get("rows_out", 0) - deleted
    batch.counters["rows_linked_again"] = batch.counters.get("rows_linked_again", 0) + deleted
    cursor.execute("DELETE FROM handovers WHERE rowid > ?", (back.handover_row,))
    cursor.execute("DELETE FROM snapshots WHERE clock > ?", (back.clock,))
    taken_back = roll_back(cursor, back.clock, back.event_row, after_row=back.log_row)
    if batch.analytics is not None:
        keep_published(taken_back, [batch.analytics])


def _write_inputs(cursor: sqlite3.Cursor, batch: LinkerBatch) -> None:
    for operation, plane, value in batch.inputs:
        if operation == "cut":
            cursor.execute("DELETE FROM inputs WHERE plane = ? AND timestamp > ?",
                           (int(plane), float(value)))
            continue
        cursor.executemany(
            "INSERT INTO inputs (plane, timestamp, frame, track_id, x, y, class_id) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            zip([int(plane)] * len(value), value.timestamp.tolist(), value.frame.tolist(),
                value.track_id.tolist(), value.world_xy[:, 0].tolist(),
                value.world_xy[:, 1].tolist(), value.class_id.tolist(), strict=True))
    cursor.executemany("INSERT OR IGNORE INTO corrections VALUES (?, ?, ?)", batch.corrections)
    if batch.correcting is not None:
        _set_meta(cursor, "correcting",
                  {str(plane): value for plane, value in batch.correcting.items()})


def _write_snapshot(cursor: sqlite3.Cursor, snapshot: dict[str, Any]) -> None:
    """Save a snapshot after the batch's rows, and forget what no snapshot needs."""
    (track_row,) = cursor.execute("SELECT COALESCE(MAX(row), 0) FROM tracks").fetchone()
    (handover_row,) = cursor.execute("SELECT COALESCE(MAX(rowid), 0) FROM handovers").fetchone()
    (event_row,) = cursor.execute("SELECT COALESCE(MAX(id), 0) FROM events").fetchone()
    (log_row,) = cursor.execute("SELECT COALESCE(MAX(rowid), 0) FROM count_log").fetchone()
    cursor.execute(
        "INSERT OR REPLACE INTO snapshots VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
        (snapshot["clock"], snapshot["emitted_until"], track_row, handover_row, event_row,
         log_row, json.dumps(snapshot["state"]),
         None if snapshot.get("analytics") is None else json.dumps(snapshot["analytics"])))
    # Kept: every snapshot of the horizon, and the newest one before it (so a correction
    # anywhere in the horizon has one at or before it).
    cursor.execute("DELETE FROM snapshots WHERE clock < (SELECT MAX(clock) FROM snapshots "
                   "WHERE clock <= ?)", (snapshot["clock"] - SNAPSHOT_HORIZON_S,))
    oldest = cursor.execute("SELECT clock, log_row FROM snapshots ORDER BY clock LIMIT 1"
                            ).fetchone()
    cursor.execute("DELETE FROM inputs WHERE timestamp <= ?", (oldest[0],))
    cursor.execute("DELETE FROM corrections WHERE timestamp <= ?", (oldest[0],))
    cursor.execute("DELETE FROM count_log WHERE rowid <= ?", (oldest[1],))


def _set_meta(cursor: sqlite3.Cursor, key: str, value: Any) -> None:
    cursor.execute("INSERT INTO meta (key, value) VALUES (?, ?) "
                   "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                   (key, json.dumps(value)))


def _identity(path: Path) -> tuple[int, int]:
    status = os.stat(path)
    return status.st_dev, status.st_ino


def _check_file(path: Path, read_only: bool) -> None:
    if not path.parent.is_dir():
        raise LinkerStoreError(f"the folder {path.parent} of the database {path.name} does not "
                               "exist; create it first.")
    if not path.exists():
        if read_only:
            raise LinkerStoreError(f"linker database {path} does not exist.")
        return
    if not path.is_file():
        raise LinkerStoreError(f"{path} is not a file.")
    with path.open("rb") as handle:
        header = handle.read(len(SQLITE_HEADER))
    if header != SQLITE_HEADER:
        raise LinkerStoreError(f"{path} is not a SQLite database (a cblrs linker database is "
                               "one); give another --db.")
