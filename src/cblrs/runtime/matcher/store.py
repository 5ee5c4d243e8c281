"""The matcher's durable state in one SQLite file (WAL mode).

Its tables, and the statements other modules run inside its transactions, are in
:mod:`~cblrs.runtime.matcher.store_schema`; the rows of messages and tracks in
:mod:`~cblrs.runtime.matcher.store_rows`; the file (its checks, private mode, writers' lock,
transaction; it holds people's positions) in :mod:`~cblrs.runtime.matcher.store_file`.

Processing a timestamp group is one transaction (track rows + inbox rows marked processed +
matcher state, or the group's ``replay`` row + counters), so after a crash the file holds
either all of a group or none of it, and a restarted matcher resumes from exactly the last
committed group.

One matcher service writes at a time, from two processes: its own (the inbox) and its tracker
process (the groups), which take turns through a lock shared by :meth:`RuntimeStore.share`;
readers (``cblrs matcher --stats``) may open the file concurrently. A service holds the file
exclusively (:meth:`RuntimeStore.hold`, a lock on ``<file>-matcher.lock``), so a second
matcher on the same file is refused.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sqlite3
import threading
import uuid
from collections.abc import Callable, Iterable, Mapping, MutableMapping, Sequence
from pathlib import Path
from typing import Any

from cblrs.detections import Tracks
from cblrs.runtime.matcher.store_file import (
    SharedStore,
    StoreError,
    WriterLock,
    _check_file,
    _check_ready,
    _create_private,
    _identity,
    _make_private,
    _Transaction,
)
from cblrs.runtime.matcher.store_rows import (
    INSERT_TRACKS,
    InboxEntry,
    StoredMessage,
    _decoder,
    _encoder,
    message_from_row,
    track_rows,
    tracks_from_rows,
)
from cblrs.runtime.matcher.store_schema import (
    _INSERT_INBOX,
    _OWN_TABLES,
    _SCHEMA,
    LATE,
    PENDING,
    SCHEMA_VERSION,
    _add_counters,
    _conflicts,
    _set_meta,
    check_tracker,
    set_matcher_state,
)


class RuntimeStore:
    """The SQLite file of one matcher (one plane).

    Args:
        path: the database file (created with its tables when missing).
        read_only: open for reading only (``--stats``); the file must exist
            (:class:`StoreNotReady` while its matcher is still creating it).
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
                _check_ready(self._connection, self.path)
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


