"""Replay of a stored run: a matcher's SQLite file played back to the page at 1x-10x.

:class:`StoreReplay` reads the track rows and analytics events a matcher stored (read-only,
beside a running matcher too) and yields the same messages as the live feed
(:mod:`cblrs.dashboard.feed`), paced by their capture times divided by the speed. The counts
the page shows during a replay are those of the stored events up to the replay's time
(events trimmed by retention are not counted); a ``counts`` message gives the totals before
the replay's start.

Reading a stored run scans its tables (``info``: a second for two million rows), so none of
it runs on the server's event loop: :class:`StoredRunInfo` reads the run's summary in a
thread at most once every :data:`INFO_MAX_AGE_S` whoever asks, and a replay reads its rows
and events in threads. Before, every ``/api/replay/info`` scanned the tracks on the loop: one
viewer asking it over and over stopped every page, stream and login of the dashboard.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import defaultdict
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.errors import CblrsError
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.analytics_store import read_events

SPEEDS = (1.0, 2.0, 5.0, 10.0)
MAX_SPEED = 10.0
CHUNK_ROWS = 5000
TICK_S = 0.2
"""Wall seconds between messages while nothing happens (so stale marks go)."""
MAX_GAP_S = 5.0
"""A stretch of capture time without rows longer than this is shortened to ``TICK_S``."""
INFO_MAX_AGE_S = 10.0
"""A stored run's summary is read again at most this often (a matcher may still write it)."""


class ReplayError(CblrsError):
    """The stored run cannot be replayed (no such file, not a matcher database, empty)."""


class StoreReplay:
    """A matcher database to replay (see the module docstring).

    Args:
        path: the matcher's SQLite file (``cblrs matcher --db``).
        to_site: maps (N, 2) pseudo positions to site metres, for the database of a matcher
            on a pseudo site (:meth:`cblrs.privacy.PseudoKey.to_site`); None: as stored.

    Raises:
        ReplayError: the file is missing or not a matcher database.
    """

    def __init__(self, path: str | Path, to_site: Callable[[Any], Any] | None = None):
        self.path = Path(path)
        self.to_site = to_site
        try:
            self._store = RuntimeStore(self.path, read_only=True)
            self._store.query("SELECT 1 FROM tracks LIMIT 1")
        except CblrsError as error:
            raise ReplayError(f"cannot replay {self.path}: {error}") from None
        except Exception as error:  # sqlite3 errors: another program's file
            raise ReplayError(f"cannot replay {self.path}: {error}.") from None

    def close(self) -> None:
        """Close the database."""
        self._store.close()

    def info(self) -> dict[str, Any]:
        """``{"start", "end", "rows", "tracks", "events", "database"}`` of the stored run
        (``database``: the file's name; viewers read this, and the server's folders are not
        theirs to know)."""
        ((start, end, rows, tracks),) = self._store.query(
            "SELECT MIN(timestamp), MAX(timestamp), COUNT(*), COUNT(DISTINCT track_id) "
            "FROM tracks"
        )
        ((events,),) = self._store.query("SELECT COUNT(*) FROM events")
        return {"start": start, "end": end, "rows": int(rows), "tracks": int(tracks),
                "events": int(events), "database": self.path.name}

    def counts_before(self, timestamp: float) -> dict[str, Any]:
        """The counts of the stored events before ``timestamp`` (the page's starting point)."""
        lines: dict[str, dict[str, int]] = defaultdict(lambda: {"positive": 0, "negative": 0})
        zones: dict[str, dict[str, float]] = defaultdict(
            lambda: {"entries": 0, "exits": 0, "visits": 0, "dwell_s": 0.0})
        open_visits: dict[str, dict[int, float]] = defaultdict(dict)
        for stored in read_events(self._store, until_timestamp=math.nextafter(timestamp, -1e300)):
            _count(stored.body, lines, zones, open_visits)
        return {"type": "counts", "lines": lines, "zones": zones,
                "open": {zone: list(visits.items()) for zone, visits in open_visits.items()}}

    async def messages(
        self, speed: float = 1.0, start: float | None = None,
        info: dict[str, Any] | None = None,
    ) -> AsyncIterator[dict[str, Any]]:
        """The stored run as page messages, paced at ``speed`` times the capture rate (the
        database is read in threads, never on the event loop).

        Args:
            speed: 1 to :data:`MAX_SPEED`.
            start: capture time to start from (default: the first row).
            info: the run's :meth:`info` if known (:class:`StoredRunInfo`), else read here.

        Raises:
            ReplayError: a speed out of range, or a run with no track rows.
        """
        if not (math.isfinite(speed) and 1.0 <= speed <= MAX_SPEED):
            raise ReplayError(f"replay speed must be 1 to {MAX_SPEED:g}, got {speed}.")
        if info is None:
            info = await asyncio.to_thread(self.info)
        if info["start"] is None:
            raise ReplayError(f"{self.path} holds no track rows to replay.")
        start = info["start"] if start is None else max(float(start), info["start"])
        yield {"type": "hello", "mode": "replay", "speed": speed, **info}
        yield await asyncio.to_thread(self.counts_before, start)
        events = await asyncio.to_thread(self._events_from, start)
        event_index = 0
        origin_wall = time.monotonic()
        origin_t = start
        last_sent_t = start
        async for t, rows in self._frames(start):
            # Long quiet stretches are shortened, so a replay does not stall for minutes.
            if t - last_sent_t > MAX_GAP_S:
                origin_t += (t - last_sent_t) - TICK_S * speed
            while True:
                due = origin_wall + (t - origin_t) / speed
                wait = due - time.monotonic()
                if wait <= 0:
                    break
                await asyncio.sleep(min(wait, TICK_S))
                if wait > TICK_S:
                    now_t = origin_t + (time.monotonic() - origin_wall) * speed
                    yield {"type": "tracks", "t": min(now_t, t), "rows": [], "tick": True}
            while event_index < len(events) and events[event_index]["timestamp"] <= t:
                yield {"type": "event", **events[event_index]}
                event_index += 1
            yield {"type": "tracks", "t": t, "rows": rows}
            last_sent_t = t
        for body in events[event_index:]:
            yield {"type": "event", **body}
        yield {"type": "end", "t": last_sent_t}

    def _events_from(self, start: float) -> list[dict[str, Any]]:
        """The stored events from ``start`` on, in time order."""
        events = [self._event(stored.body) for stored in read_events(self._store)
                  if stored.body["timestamp"] >= start]
        events.sort(key=lambda body: body["timestamp"])
        return events

    def _event(self, body: dict[str, Any]) -> dict[str, Any]:
        """An event body, its position mapped to the site for a pseudo-coordinate database."""
        if self.to_site is None or body.get("world_xy") is None:
            return body
        return {**body, "world_xy": self.to_site(np.array([body["world_xy"]]))[0].tolist()}

    async def _frames(self, start: float) -> AsyncIterator[tuple[float, list[list[Any]]]]:
        """``(capture time, rows)`` per instant from ``start`` on, read in chunks."""
        after = 0
        pending_t: float | None = None
        pending: list[list[Any]] = []
        while True:
            rows = await asyncio.to_thread(
                self._store.query,
                "SELECT row, timestamp, track_id, x, y, class_id FROM tracks "
                "WHERE row > ? AND timestamp >= ? ORDER BY row LIMIT ?",
                (after, start, CHUNK_ROWS),
            )
            if not rows:
                break
            after = rows[-1][0]
            rows.sort(key=lambda row: (row[1], row[0]))
            if self.to_site is not None and rows:
                moved = self.to_site(np.array([[row[3], row[4]] for row in rows]))
                rows = [(*row[:3], float(x), float(y), row[5])
                        for row, (x, y) in zip(rows, moved, strict=True)]
            for _, timestamp, track, x, y, klass in rows:
                if pending_t is not None and timestamp != pending_t:
                    yield pending_t, pending
                    pending = []
                pending_t = timestamp
                pending.append([track, round(x, 2), round(y, 2),
                                CLASS_NAMES[klass] if klass is not None
                                and 0 <= klass < len(CLASS_NAMES) else None])
            await asyncio.sleep(0)
        if pending_t is not None:
            yield pending_t, pending


class StoredRunInfo:
    """The summary of a stored run (:meth:`StoreReplay.info`), read in a thread, one read at
    a time, at most once every ``max_age_s``: asking for it costs the server nothing however
    often anyone asks.

    Args:
        open_replay: opens the stored run (raises :class:`ReplayError`).
        max_age_s: a summary this old is read again.
        clock: monotonic seconds.
    """

    def __init__(self, open_replay: Callable[[], StoreReplay],
                 max_age_s: float = INFO_MAX_AGE_S, clock: Callable[[], float] = time.monotonic):
        self.open_replay, self.max_age_s, self.clock = open_replay, max_age_s, clock
        self._info: dict[str, Any] | None = None
        self._read_at = -math.inf
        self._lock: asyncio.Lock | None = None

    async def get(self) -> dict[str, Any]:
        """The run's summary (``ReplayError``: it cannot be read)."""
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            if self._info is None or self.clock() - self._read_at > self.max_age_s:
                self._info = await asyncio.to_thread(self._read)
                self._read_at = self.clock()
            return self._info

    def _read(self) -> dict[str, Any]:
        replay = self.open_replay()
        try:
            return replay.info()
        finally:
            replay.close()


def _count(body: dict[str, Any], lines: dict, zones: dict, open_visits: dict) -> None:
    kind, place = body["kind"], body["place"]
    if kind == "line_crossed":
        lines[place][body["direction"]] += 1
    elif kind == "zone_entered":
        if body.get("crossed"):
            zones[place]["entries"] += 1
        open_visits[place][body["track"]] = body["timestamp"]
    elif kind == "zone_left":
        zone = zones[place]
        zone["visits"] += 1
        zone["dwell_s"] += body["dwell_s"]
        if body.get("exited"):
            zone["exits"] += 1
        open_visits[place].pop(body["track"], None)
