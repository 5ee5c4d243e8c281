"""A camera's spool: its messages on disk until the matcher confirms it has stored them.

Every message a camera node produces is written here first and deleted only when the
plane's matcher confirms, on ``cblrs/<plane>/<camera>/stored``
(:mod:`cblrs.runtime.matcher.confirmations`), that it is in the matcher's database. A message thus
survives a broker that is away for hours (only the spool's size bounds the outage), a broker
that drops it after acknowledging it (a full queue, no matcher subscribed yet, a crash between
two saves), and a restart of the camera process: a reopened spool sends everything it holds
again, oldest first.

States of a message (column ``state``):

* ``waiting``: to be handed to the transport (again);
* ``handed``: with the transport, no answer from the broker yet;
* ``acknowledged``: the broker accepted it (``acked_at`` says when); waiting for the matcher.

Bounded: when a new message would make the payloads exceed ``max_bytes``, the oldest messages
are deleted (whatever their state), counted in ``dropped`` (kept in the file) and reported by
a log line at ERROR level, at most one every 10 s. The newest data is kept because a network
of cameras is watched live; an operator who prefers the oldest sets a larger spool.

Runs. A spool never mixes two runs' data. Each message is kept with the identity of the run
that produced it (``run``: for ``cblrs camera`` its source, epoch, plane and first sequence
number). A new message is refused (:class:`SpoolConflict`, one sentence) when the spool still
holds unconfirmed messages of another run, or holds a message of the same camera and sequence
number with other content: a replay numbers its messages from 0, so two runs' messages share
numbers and the matcher, which keeps one message per camera and sequence, would take one for
the other. Delivering an earlier run's leftovers without producing anything new (a camera
with an empty source) is allowed. Repeating the same run (same identity and the same
messages) continues it: what is still spooled is not spooled twice.

The file is SQLite in WAL mode with ``synchronous=NORMAL``: a message written survives a crash
of the camera process; an OS crash may lose the last few. One process holds a spool at a
time (a lock on ``<file>-lock``); its mode is 0600.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from cblrs.errors import CblrsError

logger = logging.getLogger(__name__)

DEFAULT_SPOOL_BYTES = 512 * 1024 * 1024
"""Default bound of a spool's payloads: about 9 hours of a 30 fps camera sending 2-person
messages of ~550 bytes (measured on WILDTRACK replays), or 19 hours at 15 fps."""

WAITING, HANDED, ACKNOWLEDGED = 0, 1, 2
_DROP_LOG_INTERVAL_S = 10.0

_SCHEMA = """
CREATE TABLE IF NOT EXISTS outbox (
    sequence INTEGER PRIMARY KEY,
    topic TEXT NOT NULL,
    payload BLOB NOT NULL,
    state INTEGER NOT NULL DEFAULT 0,
    acked_at REAL
);
CREATE INDEX IF NOT EXISTS outbox_state ON outbox (state, sequence);
CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL);
"""


RUN_OPTIONS = ("camera", "detections", "dataset", "video", "images", "frames", "fps", "format",
               "aicity_camera", "frame_step", "class_name", "detector", "model", "weights",
               "confidence", "live", "realtime", "speed", "hidden_feet", "epoch",
               "first_sequence")
"""The ``cblrs camera`` options that shape its messages (its run's identity)."""
_RUN_FILES = ("detections", "dataset", "video", "images", "model", "weights")


def run_identity(options: dict[str, Any], plane_id: int) -> str:
    """A run's identity for :class:`Spool`: the :data:`RUN_OPTIONS` given (files by their
    resolved path) and the plane. A live camera's sequence numbers come from the clock, so
    its runs never share one; a replay's start at 0 unless ``first_sequence`` is given."""
    chosen = {name: options[name] for name in RUN_OPTIONS if options.get(name) is not None}
    for name in _RUN_FILES:
        if name in chosen:  # the same file however it was named
            chosen[name] = str(Path(chosen[name]).expanduser().resolve())
    return json.dumps({"plane": plane_id, **chosen}, sort_keys=True, default=str)


class SpoolError(CblrsError):
    """The spool file cannot be used (another process holds it, or it is not a spool)."""


class SpoolConflict(SpoolError):
    """A new message would mix with another run's messages (see the module docstring)."""


class Spool:
    """The outbox of one camera (see the module docstring).

    Args:
        path: the spool file (its folder is created); None keeps it in memory (tests and
            library use: then nothing survives the process).
        max_bytes: bound of the payloads held, bytes.
        clock: monotonic clock for acknowledgement times.
        run: what identifies the run that appends messages (e.g. its source and epoch);
            None: not checked (messages of files written before runs were recorded, too).

    Raises:
        SpoolError: another process holds the file, or it is not a spool.
    """

    def __init__(
        self,
        path: str | os.PathLike | None,
        *,
        max_bytes: int = DEFAULT_SPOOL_BYTES,
        clock: Callable[[], float] = time.monotonic,
        run: str | None = None,
    ):
        self.run = run
        self._others = 0  # messages of other runs held (re-counted before refusing)
        if max_bytes <= 0:
            raise SpoolError(f"the spool size must be positive, got {max_bytes} bytes.")
        self.path = None if path is None else Path(path)
        self.max_bytes = int(max_bytes)
        self._clock = clock
        self._lock = threading.RLock()
        self.taken_again = 0
        """Messages :meth:`take` handed out that a broker had acknowledged before (sent
        again), since this spool was opened."""
        self._holder: Any = None
        self._last_drop_log = -float("inf")
        self._dropped_since_log = 0
        if self.path is None:
            target = ":memory:"
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._hold()
            if not self.path.exists():
                os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
            target = str(self.path)
        try:
            self._db = sqlite3.connect(target, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.executescript(_SCHEMA)
            columns = {row[1] for row in self._db.execute("PRAGMA table_info(outbox)")}
            if "run" not in columns:  # a file written before runs were recorded
                self._db.execute("ALTER TABLE outbox ADD COLUMN run TEXT")
            # Whatever was handed or acknowledged by a broker in an earlier run has not been
            # confirmed: send it again.
            self._db.execute("UPDATE outbox SET state = 0, acked_at = NULL WHERE state != 0")
            (total,) = self._db.execute(
                "SELECT COALESCE(SUM(LENGTH(payload)), 0) FROM outbox"
            ).fetchone()
        except sqlite3.DatabaseError as error:
            self._release_hold()
            raise SpoolError(f"{self.path} is not a usable spool file: {error}.") from None
        self._bytes = int(total)
        self._others = self._count_others()
        # Earlier runs handed every sequence below this to a transport (confirmed or not): a
        # message of this run with such a sequence may be in a backbone's stream already.
        row = self._db.execute("SELECT value FROM counters WHERE name = 'handed_below'"
                               ).fetchone()
        self.handed_before = int(row[0]) if row else 0
        if self.path is not None:
            for suffix in ("", "-wal", "-shm"):
                try:
                    os.chmod(f"{self.path}{suffix}", 0o600)
                except OSError:
                    pass

    # -- lifecycle ---------------------------------------------------------------------------

    def close(self) -> None:
        with self._lock:
            self._db.close()
            self._release_hold()

    def __enter__(self) -> Spool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _hold(self) -> None:
        assert self.path is not None
        lock_path = f"{self.path}-lock"
        handle = os.fdopen(os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o600), "r+")
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            owner = handle.read().strip() or "another process"
            handle.close()
            raise SpoolError(
                f"the spool {self.path} is in use by {owner}: is this camera already running? "
                "(give another --spool to run a second one)"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()}\n")
        handle.flush()
        self._holder = handle

    def _release_hold(self) -> None:
        if self._holder is not None:
            self._holder.close()
            self._holder = None

    # -- writing -----------------------------------------------------------------------------

    def append(self, sequence: int, topic: str, payload: bytes) -> bool:
        """Keep a new message (``waiting``); False if the spool already holds this very
        message (same number and content: the same run, repeated).

        Raises:
            SpoolConflict: the spool holds unconfirmed messages of another run, or another
                message under this number (see the module docstring); nothing is kept.
        """
        size = len(payload)
        with self._lock:
            if self._others and self.run is not None:
                self._others = self._count_others()
                if self._others:
                    raise SpoolConflict(self._conflict_text(
                        f"{self._others} unconfirmed messages of another run"))
            row = self._db.execute("SELECT payload FROM outbox WHERE sequence = ?",
                                   (int(sequence),)).fetchone()
            if row is not None:
                if bytes(row[0]) == bytes(payload):
                    return False
                raise SpoolConflict(self._conflict_text(
                    f"another message numbered {int(sequence)}"))
            self._make_room(size)
            self._db.execute(
                "INSERT INTO outbox (sequence, topic, payload, run) VALUES (?, ?, ?, ?)",
                (int(sequence), topic, bytes(payload), self.run),
            )
            self._bytes += size
            return True

    def _count_others(self) -> int:
        if self.run is None:
            return 0
        (count,) = self._db.execute(
            "SELECT COUNT(*) FROM outbox WHERE run IS NOT NULL AND run != ?", (self.run,)
        ).fetchone()
        return int(count)

    def _conflict_text(self, what: str) -> str:
        where = self.path or "(memory)"
        return (
            f"the spool {where} holds {what} (a different video, source, epoch or first "
            "sequence under this camera's name); they would be taken for one another. "
            f"Deliver them first (run the earlier command again, or this camera with an "
            f"empty source, once its matcher is up), or give this run another --spool "
            f"(deleting {where} discards them)"
        )

    def _make_room(self, size: int) -> None:
        if self._bytes + size <= self.max_bytes:
            return
        dropped: list[int] = []
        while self._bytes + size > self.max_bytes:
            rows = self._db.execute(
                "SELECT sequence, LENGTH(payload) FROM outbox ORDER BY sequence LIMIT 256"
            ).fetchall()
            if not rows:
                break
            needed = self._bytes + size - self.max_bytes
            chosen = []
            for sequence, length in rows:
                chosen.append(sequence)
                needed -= length
                self._bytes -= length
                if needed <= 0:
                    break
            self._db.executemany("DELETE FROM outbox WHERE sequence = ?",
                                 [(value,) for value in chosen])
            dropped.extend(chosen)
        if dropped:
            self._add_counter("dropped", len(dropped))
            self._dropped_since_log += len(dropped)
            now = self._clock()
            if now - self._last_drop_log >= _DROP_LOG_INTERVAL_S:
                logger.error(
                    "spool %s is full (%.3g MiB): dropped the %d oldest messages no matcher had "
                    "confirmed (up to sequence %d); they are lost. Bring the matcher or broker "
                    "back, or give a larger spool.", self.path or "(memory)",
                    self.max_bytes / 2**20, self._dropped_since_log, dropped[-1],
                )
                self._last_drop_log = now
                self._dropped_since_log = 0

    def take(self, limit: int) -> list[tuple[int, str, bytes]]:
        """Up to ``limit`` waiting messages, oldest first, now ``handed``."""
        with self._lock:
            rows = self._db.execute(
                "SELECT sequence, topic, payload, acked_at IS NOT NULL FROM outbox "
                "WHERE state = 0 ORDER BY sequence LIMIT ?",
                (int(limit),),
            ).fetchall()
            self.taken_again += sum(int(row[3]) for row in rows)
            if rows:
                self._db.executemany("UPDATE outbox SET state = 1 WHERE sequence = ?",
                                     [(row[0],) for row in rows])
                self._db.execute(
                    "INSERT INTO counters (name, value) VALUES ('handed_below', ?) "
                    "ON CONFLICT(name) DO UPDATE SET value = MAX(value, excluded.value)",
                    (max(int(row[0]) for row in rows) + 1,))
        return [(int(sequence), topic, bytes(payload)) for sequence, topic, payload, _ in rows]

    def acknowledged(self, sequence: int) -> None:
        """The broker accepted ``sequence``."""
        with self._lock:
            self._db.execute(
                "UPDATE outbox SET state = 2, acked_at = ? WHERE sequence = ? AND state = 1",
                (self._clock(), int(sequence)),
            )

    def not_sent(self, sequence: int) -> None:
        """The transport gave ``sequence`` back (closed first): waiting again."""
        with self._lock:
            self._db.execute("UPDATE outbox SET state = 0 WHERE sequence = ? AND state = 1",
                             (int(sequence),))

    def confirm(self, sequences: Iterable[int]) -> int:
        """The matcher stored (or rejected) these: forget them; returns how many were held."""
        values = [(int(value),) for value in sequences]
        if not values:
            return 0
        with self._lock:
            total = 0
            self._db.execute("BEGIN")
            try:
                for (value,) in values:
                    row = self._db.execute(
                        "DELETE FROM outbox WHERE sequence = ? RETURNING LENGTH(payload)",
                        (value,),
                    ).fetchone()
                    if row is not None:
                        total += 1
                        self._bytes -= int(row[0])
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return total

    def requeue(self, acknowledged_before: float | None = None) -> int:
        """Send again the acknowledged messages (acknowledged before the given time of
        :attr:`clock`, or all); returns how many."""
        with self._lock:
            if acknowledged_before is None:
                cursor = self._db.execute("UPDATE outbox SET state = 0 WHERE state = 2")
            else:
                cursor = self._db.execute(
                    "UPDATE outbox SET state = 0 WHERE state = 2 AND acked_at < ?",
                    (acknowledged_before,),
                )
            return int(cursor.rowcount)

    def acked_at(self, sequence: int) -> float | None:
        """When the broker acknowledged ``sequence`` (None: not acknowledged, or not held)."""
        with self._lock:
            row = self._db.execute(
                "SELECT acked_at FROM outbox WHERE sequence = ? AND state = 2", (int(sequence),)
            ).fetchone()
        return None if row is None or row[0] is None else float(row[0])

    def requeue_gaps(self, below: int, acknowledged_before: float) -> int:
        """Send again the messages numbered below ``below`` that the broker acknowledged
        before ``acknowledged_before`` and the matcher has not confirmed: the matcher stores a
        camera's messages in order, so these were lost between broker and matcher."""
        with self._lock:
            cursor = self._db.execute(
                "UPDATE outbox SET state = 0 WHERE state = 2 AND sequence < ? AND acked_at < ?",
                (int(below), float(acknowledged_before)),
            )
            return int(cursor.rowcount)

    def _add_counter(self, name: str, value: int) -> None:
        self._db.execute(
            "INSERT INTO counters (name, value) VALUES (?, ?) "
            "ON CONFLICT(name) DO UPDATE SET value = value + excluded.value",
            (name, int(value)),
        )

    # -- reading -----------------------------------------------------------------------------

    def clock(self) -> float:
        return self._clock()

    def counts(self) -> dict[str, int]:
        """Messages per state (``waiting``, ``handed``, ``acknowledged``) and ``dropped``."""
        with self._lock:
            rows = dict(self._db.execute(
                "SELECT state, COUNT(*) FROM outbox GROUP BY state"
            ).fetchall())
            dropped = self._db.execute(
                "SELECT value FROM counters WHERE name = 'dropped'"
            ).fetchone()
        return {
            "waiting": int(rows.get(WAITING, 0)),
            "handed": int(rows.get(HANDED, 0)),
            "acknowledged": int(rows.get(ACKNOWLEDGED, 0)),
            "dropped": int(dropped[0]) if dropped else 0,
        }

    def __len__(self) -> int:
        with self._lock:
            (count,) = self._db.execute("SELECT COUNT(*) FROM outbox").fetchone()
        return int(count)

    @property
    def bytes(self) -> int:
        """Payload bytes held."""
        return self._bytes

    def oldest_acknowledged(self) -> float | None:
        """When the oldest message still waiting for the matcher was acknowledged."""
        with self._lock:
            (value,) = self._db.execute(
                "SELECT MIN(acked_at) FROM outbox WHERE state = 2"
            ).fetchone()
        return None if value is None else float(value)
