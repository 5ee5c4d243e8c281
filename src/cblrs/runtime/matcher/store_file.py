"""The matcher database's file: the checks before opening it, its private mode, the lock
its writers take turns with and the write transaction.

The file holds people's positions: it is created with mode 0600 (SQLite gives its ``-wal``
and ``-shm`` files the same mode), an existing one is set to 0600 when opened for writing.
Opening refuses, with one sentence, a missing folder (nothing is created silently), an empty
file and a file that is not a SQLite database or holds another program's tables. Every
transaction checks that the path still names the file that was opened: a database deleted or
replaced under a running matcher fails the next commit (:class:`StoreError`), so nothing more
is acknowledged into a file nobody will ever read.

The writers of one database (the matcher's process and its tracker process) take turns through a
:class:`WriterLock`; :class:`SharedStore` is what the other process needs to open it, and
:func:`checkpoint_regularly` copies the WAL into the file while they write.
"""

from __future__ import annotations

import fcntl
import logging
import os
import sqlite3
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cblrs.errors import CblrsError

SQLITE_HEADER = b"SQLite format 3\x00"


class StoreError(CblrsError):
    """The runtime database cannot be opened or does not belong to this matcher."""


class StoreNotReady(StoreError):
    """Opened for reading, the database is still being created by its matcher: the file is
    empty or its tables are not all written yet. A reader that polls a starting matcher
    (``--stats`` in a loop, a test, the live experiment) may try again."""


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
    if not header and read_only:
        raise StoreNotReady(
            f"{path} is an empty file: a matcher is still creating it, or it is not a cblrs "
            "matcher database; try again once the matcher has started."
        )
    if not header:
        raise StoreError(
            f"{path} is an empty file, not a cblrs matcher database; delete it to start a new "
            "database, or give the right --db."
        )
    if header != SQLITE_HEADER:
        raise StoreError(f"{path} is not a SQLite database (a cblrs matcher database is one).")


def _check_ready(connection: sqlite3.Connection, path: Path) -> None:
    """Refuse (:class:`StoreNotReady`) a database whose matcher has not finished creating it:
    the schema version is written after every table and column."""
    tables = connection.execute("SELECT 1 FROM sqlite_master WHERE name = 'meta'").fetchone()
    row = tables and connection.execute(
        "SELECT 1 FROM meta WHERE key = 'schema_version'"
    ).fetchone()
    if not row:
        raise StoreNotReady(
            f"{path} holds no matcher tables yet: a matcher is still creating it, or it "
            "never finished; try again once the matcher has started."
        )


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
