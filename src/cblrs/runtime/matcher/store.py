"""The matcher's durable state in one SQLite file (WAL mode).

Tables:

* ``inbox`` — every accepted camera message, unique by ``(camera_id, sequence)``; the key is
  the de-duplication set, so a re-delivered message is recognised across restarts. It is a
  rowid table with a unique index: rows of a few hundred bytes insert about twice as fast as
  in the ``WITHOUT ROWID`` table of earlier files, which open and work the same. A row is
  ``pending`` until its timestamp group has been tracked (then ``processed``), or ``late``
  when it arrived after its timestamp had already been released (``processed`` too once
  re-tracking has tracked it, :mod:`cblrs.runtime.matcher.retrack`).
* ``tracks`` — the tracker's output rows (frame, timestamp, track id, world x/y, camera, box).
* ``meta`` — the matcher state snapshot (``get_state()`` JSON), the last released timestamp,
  the service settings and the token of the service currently tracking (:meth:`claim`).
* ``replay`` — the groups committed since the matcher state was last saved, in order
  (``timestamp``, ``keys``: JSON ``[[camera, sequence], ...]``). The state (a few hundred kB
  of JSON with many cameras) is not saved with every group: a resumed matcher restores it
  and updates it with these groups again, which gives the state after the last committed
  group (:meth:`RuntimeStore.replay_groups`); saving the state empties the table.
* ``counters`` — received, rejected by reason, duplicates, late, processed, ...
* ``snapshots`` — the matcher's state every few seconds of capture time, for re-tracking
  late messages (:mod:`cblrs.runtime.matcher.retrack`, which owns that table's SQL).
* ``events``, ``counts``, ``count_bins``, ``od`` — the online analytics' outbox of events
  and its persistent counters (:mod:`cblrs.runtime.outputs.analytics_store`), written in the
  transaction of the group whose tracks produced them.

Processing a timestamp group is one transaction (track rows + inbox rows marked processed +
matcher state, or the group's ``replay`` row + counters), so after a crash the file holds
either all of a group or none of it, and a restarted matcher resumes from exactly the last
committed group.

One matcher service writes at a time, from two processes: its own (the inbox) and its tracker
process (the groups), which take turns through a lock shared by :meth:`RuntimeStore.share`;
readers (``cblrs matcher --stats``) may open the file concurrently. A service holds the file
exclusively (:meth:`RuntimeStore.hold`, a lock on ``<file>-matcher.lock``), so a second
matcher on the same file is refused.

The file holds people's positions: it is created with mode 0600 (SQLite gives its ``-wal``
and ``-shm`` files the same mode), an existing one is set to 0600 when opened for writing.
Opening refuses, with one sentence, a missing folder (nothing is created silently), an empty
file and a file that is not a SQLite database or holds another program's tables. Every
transaction checks that the path still names the file that was opened: a database deleted or
replaced under a running matcher fails the next commit (:class:`StoreError`), so nothing more
is acknowledged into a file nobody will ever read.

It stays one module because the schema, the transactions and every query that reads it must
change together: a newcomer changing a table finds all of its SQL here.
"""

from __future__ import annotations

import fcntl
import json
import logging
import math
import os
import socket
import sqlite3
import threading
import uuid
from collections.abc import Callable, Iterable, Mapping, MutableMapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import msgspec
import numpy as np

from cblrs.detections import CameraMessage, Tracks
from cblrs.errors import CblrsError
from cblrs.runtime.outputs.analytics_store import ANALYTICS_SCHEMA
from cblrs.runtime.wire import CLASS_IDS, WireMessage

SCHEMA_VERSION = 1
SQLITE_HEADER = b"SQLite format 3\x00"
_OWN_TABLES = frozenset({"inbox", "tracks", "meta", "counters"})

PENDING = "pending"
PROCESSED = "processed"
LATE = "late"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS inbox (
    camera_id TEXT NOT NULL,
    sequence INTEGER NOT NULL,
    timestamp REAL NOT NULL,
    frame INTEGER NOT NULL,
    received_at REAL NOT NULL,
    status TEXT NOT NULL,
    body TEXT NOT NULL,
    UNIQUE (camera_id, sequence)
);
CREATE INDEX IF NOT EXISTS inbox_pending ON inbox (status, timestamp);
CREATE TABLE IF NOT EXISTS tracks (
    row INTEGER PRIMARY KEY AUTOINCREMENT,
    frame INTEGER NOT NULL,
    timestamp REAL NOT NULL,
    track_id INTEGER NOT NULL,
    x REAL NOT NULL,
    y REAL NOT NULL,
    camera INTEGER NOT NULL,
    x_min REAL, y_min REAL, x_max REAL, y_max REAL,
    class_id INTEGER
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS replay (
    position INTEGER PRIMARY KEY AUTOINCREMENT,
    timestamp REAL NOT NULL,
    keys TEXT NOT NULL
);
""" + ANALYTICS_SCHEMA


class StoreError(CblrsError):
    """The runtime database cannot be opened or does not belong to this matcher."""


@dataclass(frozen=True)
class StoredMessage:
    """An inbox row with its decoded message."""

    message: CameraMessage
    status: str
    received_at: float


class InboxEntry(NamedTuple):
    """An accepted message as the inbox holds it: its header and its detections as JSON.

    What the receiver stores, orders and hands to the tracker: cheap to build from the
    decoded wire struct and to send to another process; :meth:`message` builds the numpy
    columns when they are needed.
    """

    camera_id: str
    sequence: int
    timestamp: float
    frame: int
    body: str
    """The detection columns as compact JSON (see :func:`message_body`)."""

    @classmethod
    def from_wire(cls, wire: WireMessage) -> InboxEntry:
        """The entry of a validated ``cblrs.detections/1`` payload."""
        detections = wire.detections
        body = _encoder.encode(
            {
                "xyxy": [item.box for item in detections],
                "confidence": [item.confidence for item in detections],
                "class_id": [CLASS_IDS[item.class_name] for item in detections],
                "colour": [item.colour for item in detections],
            }
        )
        return cls(wire.camera, wire.sequence, wire.timestamp, wire.frame, body.decode())

    @classmethod
    def from_message(cls, message: CameraMessage) -> InboxEntry:
        """The entry of a camera message.

        Raises:
            ValueError: a value is NaN or infinite (JSON has no such numbers).
        """
        return cls(
            message.camera_id,
            int(message.sequence),
            float(message.timestamp),
            int(message.frame),
            message_body(message),
        )

    def message(self) -> CameraMessage:
        """The camera message, with its numpy columns."""
        return message_from_row(self.camera_id, self.sequence, self.timestamp, self.frame,
                                self.body)


def message_body(message: CameraMessage) -> str:
    """The detection columns of a message as compact JSON (the inbox ``body``).

    Raises:
        ValueError: a value is NaN or infinite (JSON has no such numbers).
    """
    body = _encoder.encode(
        {
            "xyxy": message.xyxy.tolist(),
            "confidence": message.confidence.tolist(),
            "class_id": message.class_id.tolist(),
            "colour": message.colour.tolist(),
        }
    )
    if b"null" in body:  # msgspec writes NaN and infinities as null
        raise ValueError("Out of range float values are not JSON compliant")
    return body.decode()


_encoder = msgspec.json.Encoder()
_decoder = msgspec.json.Decoder()


def message_from_row(camera_id: str, sequence: int, timestamp: float, frame: int, body: str):
    """A :class:`CameraMessage` rebuilt from an inbox row (its columns and JSON body)."""
    data = _decoder.decode(body)
    return CameraMessage(
        camera_id=camera_id,
        sequence=int(sequence),
        timestamp=float(timestamp),
        frame=int(frame),
        xyxy=np.asarray(data["xyxy"], dtype=np.float64).reshape(-1, 4),
        confidence=np.asarray(data["confidence"], dtype=np.float64),
        class_id=np.asarray(data["class_id"], dtype=np.int64),
        colour=np.asarray(data["colour"], dtype=np.int64).reshape(-1, 3),
    )


class WriterLock:
    """The lock the writing processes of one database take turns with: ``flock`` on a file.

    The kernel releases it when the process holding it ends, so a writer killed in the middle
    of a transaction cannot leave the other one waiting forever. Each process opens the lock
    file itself (a pickled lock is its path), and each open file is a lock of its own, so two
    stores of one process exclude each other too.

    Args:
        path: the lock file (created when missing).
    """

    def __init__(self, path: Path):
        self.path = Path(path)
        self._file: Any = None

    def __getstate__(self) -> dict[str, Any]:
        return {"path": self.path, "_file": None}

    def acquire(self) -> None:
        if self._file is None:
            # Kept open: the lock belongs to the open file.
            self._file = os.fdopen(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND,
                                           0o600), "ab")
        fcntl.flock(self._file.fileno(), fcntl.LOCK_EX)

    def release(self) -> None:
        fcntl.flock(self._file.fileno(), fcntl.LOCK_UN)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


@dataclass(frozen=True)
class SharedStore:
    """What another process needs to write to the same store (see :meth:`RuntimeStore.share`).

    Attributes:
        path: the database file.
        write_lock: the lock every writer holds for its transactions.
    """

    path: Path
    write_lock: WriterLock


class RuntimeStore:
    """The SQLite file of one matcher (one plane).

    Args:
        path: the database file (created with its tables when missing).
        read_only: open for reading only (``--stats``); the file must exist.
        write_lock: the :class:`WriterLock` of the processes writing to the file (see
            :meth:`share`); None while this is the only writer.

    Raises:
        StoreError: the file is not a cblrs runtime database or cannot be opened.
    """

    def __init__(
        self, path: str | Path, read_only: bool = False, *, write_lock: WriterLock | None = None
    ):
        self.path = Path(path)
        self._lock = threading.RLock()
        self._write_lock = write_lock
        self._holder: Any = None
        self._identity: tuple[int, int] | None = None
        _check_file(self.path, read_only)
        try:
            if read_only:
                self._connection = sqlite3.connect(
                    f"file:{self.path}?mode=ro", uri=True, check_same_thread=False
                )
                self._check_tables()
            else:
                _create_private(self.path)
                self._connection = sqlite3.connect(
                    str(self.path), check_same_thread=False, isolation_level=None
                )
                self._check_tables()
                self._connection.execute("PRAGMA journal_mode=WAL")
                # WAL + NORMAL: a commit survives a process crash (the case that matters for
                # a killed matcher); only an OS crash can lose the last transactions.
                self._connection.execute("PRAGMA synchronous=NORMAL")
                self._connection.executescript(_SCHEMA)
                self._add_missing_columns()
                self._check_version()
                if write_lock is not None:
                    self._leave_checkpoints()
                _make_private(self.path)
            self._connection.execute("PRAGMA busy_timeout=5000")
        except sqlite3.DatabaseError as error:
            raise StoreError(f"{self.path} is not a usable SQLite database: {error}.") from None
        self._identity = _identity(self.path)

    # -- lifecycle -------------------------------------------------------------------------

    def close(self) -> None:
        with self._lock:
            self._connection.close()
            if self._write_lock is not None:
                self._write_lock.close()
            self.release_hold()

    def hold(self) -> None:
        """Hold the file exclusively for one matcher service until :meth:`close`.

        Raises:
            StoreError: another process (a matcher still running) holds it.
        """
        if self._holder is not None:
            return
        path = self.path.with_name(self.path.name + "-matcher.lock")
        handle = os.fdopen(os.open(path, os.O_RDWR | os.O_CREAT, 0o600), "r+")
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            owner = handle.read().strip() or "another process"
            handle.close()
            raise StoreError(
                f"{self.path} is in use by another matcher ({owner}); stop it first or use "
                "another --db."
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        handle.flush()
        self._holder = handle

    def release_hold(self) -> None:
        """End :meth:`hold` (the service stopped writing; closing the store also ends it)."""
        if self._holder is not None:
            self._holder.close()
            self._holder = None

    def check_file(self) -> None:
        """Raise if the path no longer names the file this store opened.

        Raises:
            StoreError: the file (or its folder) was deleted, moved or replaced.
        """
        if self._identity is None:
            return
        try:
            current = _identity(self.path)
        except OSError:
            current = None
        if current != self._identity:
            raise StoreError(
                f"the database {self.path} was deleted or replaced while the matcher was "
                "running; nothing more is acknowledged (the messages acknowledged into it are "
                "gone with it: restore the file, or restart with --new-db)."
            )

    def database_id(self) -> str:
        """A random id given to the file when it was created (names it in the plane lease)."""
        value = self.get_meta("database_id")
        if value is None:
            value = uuid.uuid4().hex
            self.set_meta("database_id", value)
        return str(value)

    def _check_tables(self) -> None:
        rows = self._connection.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'"
        ).fetchall()
        names = {name for (name,) in rows}
        if names and not names & _OWN_TABLES:
            raise StoreError(
                f"{self.path} is a SQLite database of another program (tables "
                f"{', '.join(sorted(names)[:5])}), not a cblrs matcher database; choose "
                "another --db."
            )

    def __enter__(self) -> RuntimeStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_version(self) -> None:
        stored = self.get_meta("schema_version")
        if stored is None:
            self._execute_write(
                "INSERT INTO meta (key, value) VALUES ('schema_version', ?)",
                (json.dumps(SCHEMA_VERSION),),
            )
        elif stored != SCHEMA_VERSION:
            raise StoreError(
                f"{self.path} has runtime schema {stored}, this cblrs writes {SCHEMA_VERSION}."
            )

    def _add_missing_columns(self) -> None:
        """Columns added since a file was created (optional ones, so old rows stay valid)."""
        columns = {row[1] for row in self._connection.execute("PRAGMA table_info(tracks)")}
        if "class_id" not in columns:
            self._connection.execute("ALTER TABLE tracks ADD COLUMN class_id INTEGER")

    def _execute_write(self, sql: str, parameters: tuple = ()) -> None:
        with self._lock:
            self._connection.execute(sql, parameters)

    # -- meta ----------------------------------------------------------------------------

    def get_meta(self, key: str, default: Any = None) -> Any:
        with self._lock:
            row = self._connection.execute(
                "SELECT value FROM meta WHERE key = ?", (key,)
            ).fetchone()
        return default if row is None else json.loads(row[0])

    def set_meta(self, key: str, value: Any) -> None:
        with self._lock, self._transaction() as cursor:
            _set_meta(cursor, key, value)

    def bind(self, settings: Mapping[str, Any]) -> None:
        """Record the matcher's identity (plane, cameras) or check it matches a reopened file.

        Raises:
            StoreError: the file was written by a matcher with other settings.
        """
        stored = self.get_meta("settings")
        wanted = json.loads(json.dumps(dict(settings)))
        if stored is None:
            self.set_meta("settings", wanted)
            return
        different = sorted(
            key for key in set(stored) | set(wanted) if stored.get(key) != wanted.get(key)
        )
        if different:
            first = different[0]
            raise StoreError(
                f"{self.path} belongs to a matcher with {first}={stored.get(first)!r}, not "
                f"{wanted.get(first)!r}; use another --db or the same settings."
            )

    # -- writes ----------------------------------------------------------------------------

    def share(self) -> SharedStore:
        """Let another process write to this file too; returns what it opens the file with.

        From now on every write transaction of this store holds a :class:`WriterLock` on
        ``<file>-writers.lock``, and so does the other process's store (opened with
        ``RuntimeStore(shared.path, write_lock=shared.write_lock)``): the writers take turns
        without SQLite's busy-waiting, which sleeps for milliseconds.
        """
        with self._lock:
            if self._write_lock is None:
                self._write_lock = WriterLock(self.path.with_name(self.path.name + "-writers.lock"))
                self._leave_checkpoints()
        return SharedStore(self.path, self._write_lock)

    def _leave_checkpoints(self) -> None:
        """No checkpoints at commits of a shared store: :func:`checkpoint_regularly` does them.

        A commit that reaches SQLite's automatic checkpoint (every 1000 pages of WAL) would
        copy them into the database file and sync it while holding the writers' lock, so
        the other writer would wait for the disk.
        """
        self._connection.execute("PRAGMA wal_autocheckpoint=0")

    def _transaction(self):
        return _Transaction(self._connection, self._write_lock, self.check_file)

    def claim(self) -> str:
        """Make a new matcher service the file's tracker: returns its token for
        :meth:`commit_group`.

        A tracker process outliving its killed service may still be committing a batch; once
        a restarted service has claimed the file, such a commit fails instead of landing
        after the new service has read where to resume.
        """
        token = uuid.uuid4().hex
        self.set_meta("tracker", token)
        return token

    def insert_messages(
        self,
        messages: Sequence[tuple[InboxEntry, str, float]],
        counters: MutableMapping[str, int] | None = None,
    ) -> list[bool]:
        """Insert accepted messages into the inbox in one transaction.

        Args:
            messages: ``(entry, status, received_at)`` with status ``pending`` or ``late``
                and ``received_at`` in wall-clock seconds.
            counters: counter increments committed in the same transaction (``conflicts``
                is added to it, see below).

        Returns:
            For each message, True if it was new, False if ``(camera, sequence)`` was already
            stored (a duplicate; its row is left as it was). The counters ``accepted``,
            ``duplicates`` and ``late`` are incremented accordingly in the same transaction,
            and ``conflicts`` for duplicates whose capture time or detections differ from
            the stored message (another run of the camera reusing its numbers).
        """
        rows = [
            (entry.camera_id, entry.sequence, entry.timestamp, entry.frame, received_at, status,
             entry.body)
            for entry, status, received_at in messages
        ]
        with self._lock, self._transaction() as cursor:
            # All rows at once; only when some were stored already (redeliveries, rare), once
            # more one at a time to learn which.
            cursor.execute("SAVEPOINT batch")
            cursor.executemany(_INSERT_INBOX, rows)
            if cursor.rowcount == len(rows):
                inserted = [True] * len(rows)
            else:
                cursor.execute("ROLLBACK TO batch")
                inserted = []
                conflicts = 0
                for row in rows:
                    cursor.execute(_INSERT_INBOX, row)
                    inserted.append(cursor.rowcount == 1)
                    if not inserted[-1]:
                        conflicts += _conflicts(cursor, row)
                if conflicts and counters is not None:
                    counters["conflicts"] = counters.get("conflicts", 0) + conflicts
                elif conflicts:
                    counters = {"conflicts": conflicts}
            cursor.execute("RELEASE batch")
            totals = dict(counters or {})
            new = sum(inserted)
            late = sum(1 for flag, row in zip(inserted, rows, strict=True)
                       if flag and row[5] == LATE)
            for name, value in (("accepted", new), ("duplicates", len(inserted) - new),
                                ("late", late)):
                totals[name] = totals.get(name, 0) + value
            _add_counters(cursor, totals)
        return inserted

    def commit_group(
        self,
        keys: Iterable[tuple[str, int]],
        tracks: Tracks,
        matcher_state: Mapping[str, Any] | None,
        released_timestamp: float,
        counters: Mapping[str, int] | None = None,
        tracker: str | None = None,
        also: Callable[[sqlite3.Cursor], None] | None = None,
        replay: Sequence[tuple[float, Sequence[tuple[str, int]]]] | None = None,
    ) -> None:
        """Store one processed timestamp group (or several) atomically.

        Args:
            keys: ``(camera_id, sequence)`` of the group's messages, marked processed.
            tracks: the tracker's output for the group.
            matcher_state: the tracker's ``get_state()`` after the group (JSON-serialisable).
            released_timestamp: the group's capture timestamp, seconds.
            counters: counter increments.
            tracker: the committing service's :meth:`claim` token, if it has one.
            also: more writes of the same transaction (the online analytics' events,
                counters and state), given the cursor.
            replay: with ``matcher_state`` None, the groups as the matcher was updated with
                them (``(timestamp, keys in order)``): a resumed matcher updates the last
                saved state with them again (:meth:`replay_groups`). A state given empties
                the replay table instead.

        Raises:
            StoreError: ``tracker`` is not the file's tracker any more (nothing is written).
        """
        rows = track_rows(tracks)
        with self._lock, self._transaction() as cursor:
            if tracker is not None:
                check_tracker(cursor, self.path, tracker)
            cursor.executemany(
                "UPDATE inbox SET status = 'processed' WHERE camera_id = ? AND sequence = ?",
                [(camera_id, int(sequence)) for camera_id, sequence in keys],
            )
            cursor.executemany(INSERT_TRACKS, rows)
            if matcher_state is not None:
                set_matcher_state(cursor, matcher_state)
            elif replay:
                cursor.executemany(
                    "INSERT INTO replay (timestamp, keys) VALUES (?, ?)",
                    [(float(timestamp), _encoder.encode([[camera, int(sequence)]
                                                         for camera, sequence in group]).decode())
                     for timestamp, group in replay],
                )
            _set_meta(cursor, "released_timestamp", float(released_timestamp))
            _add_counters(cursor, counters or {})
            if also is not None:
                also(cursor)

    def save_matcher_state(self, state: Any, tracker: str | None = None,
                           also: Callable[[sqlite3.Cursor], None] | None = None) -> None:
        """Save the matcher state after the last committed group (JSON-serialisable, or
        its JSON text) and empty the replay table, in one transaction with ``also``.

        Raises:
            StoreError: ``tracker`` is not the file's tracker any more (nothing is written).
        """
        with self._lock, self._transaction() as cursor:
            if tracker is not None:
                check_tracker(cursor, self.path, tracker)
            set_matcher_state(cursor, state)
            if also is not None:
                also(cursor)

    def replay_groups(self) -> list[tuple[float, list[InboxEntry]]]:
        """The groups committed since the matcher state was saved, in order: ``(timestamp,
        entries)`` as the matcher was updated with them.

        Raises:
            StoreError: a message of them is no longer in the inbox.
        """
        with self._lock:
            groups = self._connection.execute(
                "SELECT timestamp, keys FROM replay ORDER BY position").fetchall()
            replayed = []
            for timestamp, keys in groups:
                entries = []
                for camera, sequence in _decoder.decode(keys):
                    row = self._connection.execute(
                        "SELECT camera_id, sequence, timestamp, frame, body FROM inbox "
                        "WHERE camera_id = ? AND sequence = ?", (camera, sequence)).fetchone()
                    if row is None:
                        raise StoreError(
                            f"{self.path} lacks message {sequence} of camera {camera}, which "
                            "the saved matcher state needs to resume; restart with --new-db.")
                    entries.append(InboxEntry(*row))
                replayed.append((float(timestamp), entries))
        return replayed

    def write(self, writes: Callable[[sqlite3.Cursor], Any]) -> Any:
        """Run ``writes(cursor)`` in one write transaction of its own; returns its result."""
        with self._lock, self._transaction() as cursor:
            return writes(cursor)

    def query(self, sql: str, parameters: tuple = ()) -> list[tuple]:
        """The rows of one read statement."""
        with self._lock:
            return self._connection.execute(sql, parameters).fetchall()

    def execute_write(self, sql: str, parameters: tuple = ()) -> int:
        """One write statement in its own transaction (with the file check); rows changed."""
        with self._lock, self._transaction() as cursor:
            cursor.execute(sql, parameters)
            return int(cursor.rowcount)

    def has_table(self, name: str) -> bool:
        with self._lock:
            row = self._connection.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (name,)
            ).fetchone()
        return row is not None

    def oldest_time(self, table: str, column: str) -> float | None:
        """The time column of the first row in rowid order (rows come in about time order)."""
        with self._lock:
            try:
                row = self._connection.execute(
                    f"SELECT {column} FROM {table} ORDER BY rowid LIMIT 1"
                ).fetchone()
            except sqlite3.OperationalError:  # no rowid (an inbox of early files)
                return None
        return None if row is None or row[0] is None else float(row[0])

    def used_bytes(self) -> int:
        """Bytes of the database's pages in use (free pages are reused, not counted)."""
        with self._lock:
            (pages,) = self._connection.execute("PRAGMA page_count").fetchone()
            (free,) = self._connection.execute("PRAGMA freelist_count").fetchone()
            (size,) = self._connection.execute("PRAGMA page_size").fetchone()
        return int((pages - free) * size)

    def add_counters(self, counters: Mapping[str, int]) -> None:
        with self._lock, self._transaction() as cursor:
            _add_counters(cursor, counters)

    # -- reads -----------------------------------------------------------------------------

    def counters(self) -> dict[str, int]:
        with self._lock:
            rows = self._connection.execute("SELECT name, value FROM counters").fetchall()
        return {name: int(value) for name, value in sorted(rows)}

    def matcher_state(self) -> dict | None:
        return self.get_meta("matcher_state")

    def released_timestamp(self) -> float | None:
        return self.get_meta("released_timestamp")

    def pending_entries(self) -> list[InboxEntry]:
        """The ``pending`` inbox rows, ordered by timestamp and camera."""
        with self._lock:
            rows = self._connection.execute(
                "SELECT camera_id, sequence, timestamp, frame, body FROM inbox "
                "WHERE status = ? ORDER BY timestamp, camera_id, sequence",
                (PENDING,),
            ).fetchall()
        return [InboxEntry(*row) for row in rows]

    def messages(self, status: str | None = None) -> list[StoredMessage]:
        """Inbox rows (all, or of one status) ordered by timestamp and camera."""
        sql = "SELECT camera_id, sequence, timestamp, frame, body, status, received_at FROM inbox"
        parameters: tuple = ()
        if status is not None:
            sql += " WHERE status = ?"
            parameters = (status,)
        sql += " ORDER BY timestamp, camera_id, sequence"
        with self._lock:
            rows = self._connection.execute(sql, parameters).fetchall()
        return [
            StoredMessage(message_from_row(*row[:5]), row[5], float(row[6])) for row in rows
        ]

    def inbox_summary(self) -> dict[str, dict[str, float]]:
        """Per camera: message count, highest sequence, latest timestamp and receipt time."""
        with self._lock:
            rows = self._connection.execute(
                "SELECT camera_id, COUNT(*), MAX(sequence), MAX(timestamp), MAX(received_at) "
                "FROM inbox GROUP BY camera_id"
            ).fetchall()
        return {
            camera: {
                "count": int(count),
                "max_sequence": int(sequence),
                "max_timestamp": float(timestamp),
                "max_received_at": float(received_at),
            }
            for camera, count, sequence, timestamp, received_at in rows
        }

    def status_counts(self) -> dict[str, int]:
        with self._lock:
            rows = self._connection.execute(
                "SELECT status, COUNT(*) FROM inbox GROUP BY status"
            ).fetchall()
        return {status: int(count) for status, count in rows}

    def tracks(self, after_row: int = 0, limit: int | None = None) -> Tracks:
        """Stored track rows in insertion order (all, or those after row ``after_row``)."""
        sql = (
            "SELECT frame, timestamp, track_id, x, y, camera, x_min, y_min, x_max, y_max, "
            "class_id FROM tracks WHERE row > ? ORDER BY row"
        )
        if limit is not None:
            sql += f" LIMIT {int(limit)}"
        with self._lock:
            rows = self._connection.execute(sql, (int(after_row),)).fetchall()
        return tracks_from_rows(rows)

    def summary(self) -> dict[str, Any]:
        """Counters, inbox status counts, track rows and settings, for ``--stats``.

        Raises:
            StoreError: the file is damaged (SQLite cannot read it).
        """
        try:
            return self._summary()
        except sqlite3.DatabaseError as error:
            raise StoreError(f"{self.path} is damaged: SQLite says {error}.") from None

    def _summary(self) -> dict[str, Any]:
        with self._lock:
            track_rows = self._connection.execute("SELECT COUNT(*) FROM tracks").fetchone()[0]
            identities = self._connection.execute(
                "SELECT COUNT(DISTINCT track_id) FROM tracks"
            ).fetchone()[0]
        return {
            "database": str(self.path),
            "settings": self.get_meta("settings"),
            "counters": self.counters(),
            "inbox": self.status_counts(),
            "track_rows": int(track_rows),
            "track_ids": int(identities),
            "released_timestamp": self.released_timestamp(),
        }


INSERT_TRACKS = (
    "INSERT INTO tracks (frame, timestamp, track_id, x, y, camera, "
    "x_min, y_min, x_max, y_max, class_id) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
)
"""Insert one row of :func:`track_rows` into the ``tracks`` table."""


def track_rows(tracks: Tracks) -> list[tuple]:
    """The ``tracks`` table rows of :class:`Tracks` (NaN boxes and class -1 as NULL)."""
    if not len(tracks):
        return []
    # Whole columns to Python numbers at once (``tolist`` gives the same ints and floats as
    # converting element by element, several times faster with WILDTRACK-sized groups).
    boxes = np.asarray(tracks.xyxy, dtype=np.float64)
    box_values: list[list[float | None]] = boxes.tolist()
    if not np.isfinite(boxes).all():
        box_values = [[value if math.isfinite(value) else None for value in row]
                      for row in box_values]
    classes = [None if value < 0 else value for value in tracks.class_id.tolist()]
    world = tracks.world_xy.tolist()
    return [
        (frame, timestamp, track_id, x_y[0], x_y[1], camera, *box, class_id)
        for frame, timestamp, track_id, x_y, camera, box, class_id in zip(
            tracks.frame.tolist(), tracks.timestamp.tolist(), tracks.track_id.tolist(), world,
            tracks.camera_id.tolist(), box_values, classes, strict=True)
    ]


def tracks_from_rows(rows: Sequence[Sequence[Any]]) -> Tracks:
    """Track rows ``(frame, timestamp, track_id, x, y, camera, x_min, y_min, x_max, y_max,
    class_id)`` as :class:`Tracks` (NULL boxes become NaN, a NULL class -1)."""
    if not rows:
        return Tracks.empty()
    table = np.array(rows, dtype=object)
    return Tracks(
        frame=table[:, 0].astype(np.int64),
        timestamp=table[:, 1].astype(np.float64),
        track_id=table[:, 2].astype(np.int64),
        world_xy=table[:, 3:5].astype(np.float64),
        camera_id=table[:, 5].astype(np.int64),
        xyxy=np.where(table[:, 6:10] == None, np.nan, table[:, 6:10]).astype(np.float64),  # noqa: E711
        class_id=np.where(table[:, 10] == None, -1, table[:, 10]).astype(np.int64),  # noqa: E711
    )


def checkpoint_regularly(path: Path, stop: threading.Event, interval_s: float = 1.0) -> None:
    """Copy the WAL of a shared store into its database file every ``interval_s`` seconds
    until ``stop`` is set (in a thread of one of its writers, on a connection of its own).

    A passive checkpoint does not block the writers: they go on appending to the WAL. One
    that fails is tried again at the next interval and never ends the thread: a database
    deleted under the matcher failed it ("disk I/O error") and printed a traceback beside the
    one sentence the matcher says about it (the writers find and report what is wrong).
    """
    connection = sqlite3.connect(str(path), check_same_thread=False)
    try:
        while not stop.wait(interval_s):
            try:
                connection.execute("PRAGMA wal_checkpoint(PASSIVE)")
            except sqlite3.Error as error:
                logging.getLogger(__name__).debug("checkpoint of %s failed: %s", path, error)
    finally:
        connection.close()


class _Transaction:
    """``BEGIN IMMEDIATE`` ... ``COMMIT`` (or ``ROLLBACK`` on an exception), holding the
    writers' lock when the store is shared; ``check`` runs before and after (it raises if the
    file was deleted or replaced, so the caller does not acknowledge what it wrote)."""

    def __init__(
        self,
        connection: sqlite3.Connection,
        write_lock: WriterLock | None,
        check: Callable[[], None] | None = None,
    ):
        self._connection = connection
        self._write_lock = write_lock
        self._check = check

    def __enter__(self) -> sqlite3.Cursor:
        if self._check is not None:
            self._check()
        if self._write_lock is not None:
            self._write_lock.acquire()
        try:
            self._cursor = self._connection.cursor()
            self._cursor.execute("BEGIN IMMEDIATE")
        except BaseException:
            self._release()
            raise
        return self._cursor

    def __exit__(self, kind, value, traceback) -> None:
        try:
            self._cursor.execute("COMMIT" if kind is None else "ROLLBACK")
        finally:
            self._release()
        if kind is None and self._check is not None:
            self._check()

    def _release(self) -> None:
        if self._write_lock is not None:
            self._write_lock.release()


def _identity(path: Path) -> tuple[int, int]:
    status = os.stat(path)
    return status.st_dev, status.st_ino


def _check_file(path: Path, read_only: bool) -> None:
    """One sentence for every file that cannot be a matcher database (see the module)."""
    folder = path.parent
    if not folder.is_dir():
        raise StoreError(
            f"the folder {folder} of the database {path.name} does not exist; create it first "
            "(it is not created silently, so a mistyped path does not start an empty database)."
        )
    if not path.exists():
        if read_only:
            raise StoreError(f"runtime database {path} does not exist.")
        return
    if not path.is_file():
        raise StoreError(f"{path} is not a file.")
    try:
        with path.open("rb") as handle:
            header = handle.read(len(SQLITE_HEADER))
    except OSError as error:
        raise StoreError(f"cannot read {path}: {error.strerror or error}.") from None
    if not header:
        raise StoreError(
            f"{path} is an empty file, not a cblrs matcher database; delete it to start a new "
            "database, or give the right --db."
        )
    if header != SQLITE_HEADER:
        raise StoreError(f"{path} is not a SQLite database (a cblrs matcher database is one).")


def _create_private(path: Path) -> None:
    """Create ``path`` with mode 0600 if it does not exist (SQLite would use 0644)."""
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except FileExistsError:
        pass


def _make_private(path: Path) -> None:
    for name in (path.name, path.name + "-wal", path.name + "-shm"):
        try:
            os.chmod(path.with_name(name), 0o600)
        except OSError:  # not ours, or gone: nothing to do
            pass


_INSERT_INBOX = (
    "INSERT OR IGNORE INTO inbox "
    "(camera_id, sequence, timestamp, frame, received_at, status, body) "
    "VALUES (?, ?, ?, ?, ?, ?, ?)"
)


def check_tracker(cursor: sqlite3.Cursor, path: Path, tracker: str) -> None:
    """Inside a write transaction: raise unless ``tracker`` is still the file's tracker.

    Raises:
        StoreError: another service has claimed the file (:meth:`RuntimeStore.claim`).
    """
    (claimed,) = cursor.execute(
        "SELECT value FROM meta WHERE key = 'tracker'"
    ).fetchone() or (None,)
    if claimed is None or json.loads(claimed) != tracker:
        raise StoreError(f"another matcher service has taken over {path}; not committing.")


def set_matcher_state(cursor: sqlite3.Cursor, state: Any) -> None:
    """Inside a write transaction: save the matcher state (a value, or its JSON text) and
    empty the replay table (the state has seen every committed group)."""
    cursor.execute(
        "INSERT INTO meta (key, value) VALUES ('matcher_state', ?) "
        "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
        (state if isinstance(state, str) else json.dumps(state, default=_json_default),),
    )
    cursor.execute("DELETE FROM replay")


def set_meta_value(cursor: sqlite3.Cursor, key: str, value: Any) -> None:
    """Inside a write transaction: set one ``meta`` value (JSON)."""
    _set_meta(cursor, key, value)


def add_counter_values(cursor: sqlite3.Cursor, counters: Mapping[str, int]) -> None:
    """Inside a write transaction: add counter increments."""
    _add_counters(cursor, counters)


def _set_meta(cursor: sqlite3.Cursor, key: str, value: Any) -> None:
    cursor.execute(
        "INSERT INTO meta (key, value) VALUES (?, ?) "
        "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
        (key, json.dumps(value, default=_json_default)),
    )


def _add_counters(cursor: sqlite3.Cursor, counters: Mapping[str, int]) -> None:
    cursor.executemany(
        "INSERT INTO counters (name, value) VALUES (?, ?) "
        "ON CONFLICT(name) DO UPDATE SET value = value + excluded.value",
        [(name, int(value)) for name, value in counters.items() if value],
    )


def _conflicts(cursor: sqlite3.Cursor, row: tuple) -> int:
    """1 if the stored message under ``row``'s camera and sequence differs from ``row``."""
    stored = cursor.execute(
        "SELECT timestamp, frame, body FROM inbox WHERE camera_id = ? AND sequence = ?",
        (row[0], row[1]),
    ).fetchone()
    return int(stored is not None and tuple(stored) != (row[2], row[3], row[6]))


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in the matcher state")
