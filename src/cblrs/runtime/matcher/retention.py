"""Retention of the matcher's database: how long, and how much, history it keeps.

Without it the file grows for ever (about 320 MB an hour with 20 cameras at 10 fps). A
:class:`RetentionPolicy` bounds it by age and by size, and is on by default:

* **age** (``max_age_s``, default 24 h): rows whose time (a capture time, seconds since the
  Unix epoch) is older are deleted. 24 h is also how old a message may be and still be
  accepted (``ValidationPolicy.max_age_s``), so the inbox keeps recognising re-deliveries
  for as long as they can arrive;
* **size** (``max_bytes``, default 4 GiB, about 12 hours at 20 cameras x 10 fps): while the
  database's pages in use exceed it, the oldest deletable rows go first;
* **never** a message not yet tracked: only rows matching a table's ``deletable`` condition
  are deleted (for the inbox: ``processed`` or ``late``, never ``pending``). If undeletable
  rows alone exceed the size bound, nothing more is deleted and a warning says so.

SQLite reuses the freed pages, so the file stops growing at about ``max_bytes`` rather than
shrinking. A re-delivery of a message whose inbox row was deleted early by the size bound is
stored again as ``late`` (its time was released long ago), so it is never tracked twice.

Other tables join by adding a :class:`RetainedTable` (a table name, its time column and the
condition for rows that may go) to the policy's ``tables``, as the analytics' events (only
once published) and binned counts do in :data:`DEFAULT_TABLES`::

    policy = RetentionPolicy(tables=(*DEFAULT_TABLES, RetainedTable("mine", "timestamp")))

Tables missing from a database are skipped. Deletion runs in batches of ``batch_rows`` rows,
one short transaction each, so the receiver never waits long.
"""

from __future__ import annotations

import json
import logging
import math
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from cblrs.errors import CblrsError
from cblrs.runtime.matcher.store_schema import set_meta_value
from cblrs.runtime.outputs.analytics_store import RETAINED_BINS, RETAINED_EVENTS

logger = logging.getLogger(__name__)

DEFAULT_MAX_AGE_S = 24 * 3600.0
DEFAULT_MAX_BYTES = 4 * 1024**3


@dataclass(frozen=True)
class RetainedTable:
    """A table under the retention policy.

    Attributes:
        name: the table.
        time_column: its time column, seconds since the Unix epoch.
        deletable: SQL condition for rows that may be deleted ("1": any row).
    """

    name: str
    time_column: str
    deletable: str = "1"

    def __post_init__(self) -> None:
        for value in (self.name, self.time_column):
            if not value.replace("_", "").isalnum():
                raise CblrsError(f"retained table and column names must be identifiers, "
                                 f"got {value!r}.")


DEFAULT_TABLES: tuple[RetainedTable, ...] = (
    RetainedTable("inbox", "timestamp", "status IN ('processed', 'late')"),
    RetainedTable("tracks", "timestamp"),
    RetainedTable(*RETAINED_EVENTS),
    RetainedTable(*RETAINED_BINS),
    RetainedTable("alerts", "timestamp", "instr(delivered, '\"cblrs/backbone\"') > 0"),
)
"""The matcher's own tables: the inbox (never ``pending`` rows), the track history, the
analytics events (never one not yet published), the binned counts and the alerts (never one
not yet published on the backbone; :mod:`cblrs.runtime.outputs.alert_service`); the analytics'
totals (``counts``, ``od``) are kept for ever (:mod:`cblrs.runtime.outputs.analytics_store`)."""


@dataclass(frozen=True)
class RetentionPolicy:
    """How much history the matcher keeps (see the module docstring).

    Attributes:
        max_age_s: delete rows older than this, seconds (None: no age limit).
        max_bytes: keep the database's pages in use under this, bytes (None: no limit).
        interval_s: how often the service applies the policy, seconds.
        batch_rows: rows deleted per transaction, at most.
        tables: the tables it applies to.
    """

    max_age_s: float | None = DEFAULT_MAX_AGE_S
    max_bytes: int | None = DEFAULT_MAX_BYTES
    interval_s: float = 60.0
    batch_rows: int = 5000
    tables: tuple[RetainedTable, ...] = field(default=DEFAULT_TABLES)

    def __post_init__(self) -> None:
        if self.max_age_s is not None and not (math.isfinite(self.max_age_s)
                                               and self.max_age_s > 0):
            raise CblrsError(f"retention age must be a positive number of seconds, got "
                             f"{self.max_age_s}.")
        if self.max_bytes is not None and self.max_bytes <= 0:
            raise CblrsError(f"retention size must be positive, got {self.max_bytes} bytes.")
        if not (self.interval_s > 0 and self.batch_rows > 0):
            raise CblrsError("retention interval and batch size must be positive.")

    @property
    def enabled(self) -> bool:
        return self.max_age_s is not None or self.max_bytes is not None

    def describe(self) -> str:
        parts = []
        if self.max_age_s is not None:
            parts.append(f"{self.max_age_s / 3600:g} h")
        if self.max_bytes is not None:
            parts.append(f"{self.max_bytes / 2**30:g} GiB")
        return " or ".join(parts) if parts else "everything (no retention)"


def apply_retention(
    store: Any, policy: RetentionPolicy, now: float | None = None
) -> dict[str, int]:
    """Delete what ``policy`` no longer keeps from ``store`` (a RuntimeStore).

    Args:
        store: the matcher's :class:`~cblrs.runtime.matcher.store.RuntimeStore`.
        policy: the policy.
        now: the wall clock, seconds since the Unix epoch (default: now).

    Returns:
        Rows deleted per table.
    """
    now = time.time() if now is None else now
    deleted: dict[str, int] = {}
    tables = [table for table in policy.tables if store.has_table(table.name)]
    if policy.max_age_s is not None:
        cutoff = now - policy.max_age_s
        for table in tables:
            oldest = store.oldest_time(table.name, table.time_column)
            if oldest is None or oldest >= cutoff:
                continue  # nothing old enough: no need to scan the table
            deleted[table.name] = _delete(
                store, table, f"{table.time_column} < ?", (cutoff,), policy.batch_rows,
                until=None,
            )
    if policy.max_bytes is not None and store.used_bytes() > policy.max_bytes:
        limit = policy.max_bytes
        progress = True
        while store.used_bytes() > limit and progress:
            progress = False
            for table in tables:
                count = _delete(store, table, "1", (), policy.batch_rows,
                                until=lambda: store.used_bytes() <= limit, rounds=1)
                deleted[table.name] = deleted.get(table.name, 0) + count
                progress = progress or count > 0
        if store.used_bytes() > limit:
            logger.warning(
                "retention: the database %s uses %.0f MiB, more than %.0f MiB, but the rest "
                "is not yet tracked (kept)", store.path, store.used_bytes() / 2**20,
                limit / 2**20)
    total = sum(deleted.values())
    if total:
        logger.info("retention (%s): deleted %s", policy.describe(),
                    ", ".join(f"{count} {name} rows" for name, count in deleted.items() if count))
    return deleted


def _delete(
    store: Any,
    table: RetainedTable,
    condition: str,
    parameters: tuple,
    batch_rows: int,
    until: Callable[[], bool] | None,
    rounds: int | None = None,
) -> int:
    """Delete the oldest rows matching ``condition`` and the table's ``deletable``, in
    batches, until none is left, ``until()`` is true, or ``rounds`` batches were done."""
    # Rows are appended in about time order, so the oldest come first in rowid order: a
    # batch is found at the start of the table without sorting it.
    batch = (f"SELECT rowid FROM {table.name} WHERE ({table.deletable}) AND ({condition}) "
             "ORDER BY rowid LIMIT ?")
    newest = f"SELECT MAX({table.time_column}) FROM {table.name} WHERE rowid IN ({batch})"
    sql = f"DELETE FROM {table.name} WHERE rowid IN ({batch})"

    def delete_batch(cursor: sqlite3.Cursor) -> int:
        # Where deletion has reached (meta "deleted_until.<table>"): re-tracking late
        # messages (cblrs.runtime.matcher.retrack) never starts from a snapshot before it.
        (until,) = cursor.execute(newest, (*parameters, batch_rows)).fetchone()
        count = int(cursor.execute(sql, (*parameters, batch_rows)).rowcount)
        if until is not None and count:
            key = f"deleted_until.{table.name}"
            row = cursor.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
            set_meta_value(cursor, key, max(float(until), json.loads(row[0]) if row else until))
        return count

    total = 0
    done = 0
    while rounds is None or done < rounds:
        try:
            count = store.write(delete_batch)
        except sqlite3.OperationalError as error:  # e.g. a WITHOUT ROWID inbox of old files
            logger.warning("retention: cannot delete from %s: %s", table.name, error)
            return total
        total += count
        done += 1
        if count < batch_rows or (until is not None and until()):
            break
    return total
