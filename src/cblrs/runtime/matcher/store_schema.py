"""The matcher database's tables, the inbox statuses, and the statements other modules run
inside a write transaction of :class:`~cblrs.runtime.matcher.store.RuntimeStore`
(re-tracking, retention).

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
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.runtime.matcher.store_file import StoreError
from cblrs.runtime.outputs.analytics_store import ANALYTICS_SCHEMA

SCHEMA_VERSION = 1

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
