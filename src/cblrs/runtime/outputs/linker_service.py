"""The linker service: every plane's track updates in, global tracks and site counts out.

One service serves a site. It subscribes to the track updates of every plane the site has
(``cblrs/<plane>/tracks``, QoS 1, a persistent session or a durable consumer, so the planes'
matchers may run on any host of the backbone), and per batch of deliveries:

1. **decodes** each update (``cblrs.tracks/1``; a bad one is counted by reason and
   acknowledged) and **de-duplicates** it by (plane, update time): the ``updates`` table of
   its SQLite file (:class:`~cblrs.runtime.outputs.linker_store.LinkerStore`), so a redelivery, or a
   plane rebuilt on a new host publishing its updates again, is taken once;
2. gives the rows to the :class:`~cblrs.linking.PlaneLinker` and moves its **watermark** to
   the oldest plane clock (each plane's newest update time, less the largest lag seen between
   an update's time and its earliest row) minus ``delay_s``: rows are linked in time order
   once every plane has passed them. A plane silent for ``max_wait_s`` while others go on is
   left out of the watermark (a matcher that died and is not yet taken over must not stop the
   site); rows it sends later for times already linked are counted ``late_rows``. At start,
   planes never heard of are waited for ``max_wait_s`` too;
2b. follows a matcher's **corrections** (its updates with ``corrected_from``: late messages
   re-tracked, :mod:`cblrs.runtime.matcher.retrack`): the first update of a correction
   replaces the plane's rows after ``corrected_from`` (the store keeps every plane's rows,
   ``inputs``, for ``SNAPSHOT_HORIZON_S``), its later ones (the same ``corrected_from``, later
   times) add theirs; the linker goes back to its newest snapshot at or before
   ``corrected_from`` (one every ``SNAPSHOT_INTERVAL_S`` of its clock), takes back the global
   rows, hand-overs, events and counts made after it and links every plane's rows since
   again: the global rows, ids and counts are those of a linker that had the corrected rows
   from the start. A correction older than the oldest snapshot is counted
   ``corrections_unlinked`` and not linked. While a correction is under way (its updates
   have not reached the plane's clock when it began, and the plane has sent no other update
   since), the plane's part of the watermark is the correction's newest update time, not its
   clock: the times its corrected rows have yet to come for are not linked (each would send
   the linker back again), so a correction costs about one relink. Kept in the file with the
   correction; a plane silent for ``max_wait_s`` is left out as above;
3. counts the global rows that became final with the site's **analytics** (the matchers'
   engine, :class:`~cblrs.runtime.outputs.online_analytics.OnlineAnalytics`, on every place of the
   site; lives span a portal's longest transit);
4. **commits** the batch in one transaction (update keys, global rows, hand-overs, the
   linker's and the analytics' states) and only then acknowledges its deliveries: killed at
   any moment, the linker resumes from its file and the broker delivers again what it had not
   committed;
5. **publishes** the global rows on ``cblrs/0/tracks`` (plane 0: the site; empty updates too,
   each row with its ``source_plane`` and ``source_track``; after going back to a snapshot,
   with ``corrected_from``: they replace the global rows after that time), and through the
   matchers' reporter the site's events on ``cblrs/0/events`` (an outbox: published until the broker
   acknowledges) and a live summary on ``cblrs/0/live``.

:meth:`LinkerService.finish` is the end of every stream (everything watched is decided,
every row leaves, every track ends); a service stopped without it resumes where it was.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any, Literal

import numpy as np

from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.linking.linker import LinkedRows, PlaneLinker
from cblrs.runtime.outputs.analytics_service import ServiceReporter
from cblrs.runtime.outputs.linker_store import (
    SNAPSHOT_INTERVAL_S,
    LinkerBatch,
    LinkerStore,
    Snapshot,
)
from cblrs.runtime.transport.protocol import Delivery
from cblrs.runtime.transport.topics import (
    SITE_PLANE,
    TopicError,
    linker_status_topic,
    parse_tracks_topic,
    site_tracks_topic,
    tracks_topic,
)
from cblrs.runtime.wire import (
    RejectedMessage,
    RejectReason,
    decode_tracks,
    encode_status,
    encode_tracks,
)

logger = logging.getLogger(__name__)

DEFAULT_DELAY_S = 0.5
"""Rows wait this long behind the oldest plane clock (a tracker returns rows a little behind
its update's time)."""
DEFAULT_MAX_WAIT_S = 30.0
"""A plane silent this long while others go on is left out of the watermark."""
PUBLISH_ROWS = 4000
"""Global rows per published update, at most: about 660 kB (some 165 bytes a row), under the
1 MiB packets of the broker `cblrs broker-config` writes (a correction publishes every row
since its snapshot again at once)."""
MAX_FUTURE_S = 60.0
"""An update timed further ahead of the linker's clock than this is refused (one bad clock
would otherwise move a plane's watermark ahead and make every later row late)."""


class LinkerFailed(CblrsError):
    """The linking thread stopped on a failure (the database gone, a broken state)."""


class LinkerService:
    """The site's linker fed through a transport, persisted in a store (see the module).

    Args:
        transport: the backbone client (MQTT, NATS or in-process); subscribed before connect.
        store: the linker's database.
        linker: the linker (its planes and links are the site's).
        plane_ids: the planes whose tracks it reads (every plane of the site).
        site: what the store is bound to (planes, links), so a file of another site is
            refused.
        analytics: the site's analytics (None: no counting).
        publish_tracks: publish the global rows on ``cblrs/0/tracks``.
        delay_s: rows wait this long behind the oldest plane clock.
        max_wait_s: a plane silent this long while others go on is left out (see the module).
        linker_id: names its status topic.
        live_interval_s: seconds between live summaries (None: none; needs analytics).
        monotonic: the clock of ``max_wait_s`` (tests).
    """

    def __init__(
        self,
        transport: Any,
        store: LinkerStore,
        linker: PlaneLinker,
        plane_ids: Sequence[int],
        *,
        site: dict[str, Any] | None = None,
        analytics: Any = None,
        publish_tracks: bool = True,
        delay_s: float = DEFAULT_DELAY_S,
        max_wait_s: float = DEFAULT_MAX_WAIT_S,
        linker_id: str = "linker",
        live_interval_s: float | None = 1.0,
        monotonic: Callable[[], float] = time.monotonic,
    ):
        for name, value in (("delay_s", delay_s), ("max_wait_s", max_wait_s)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        self.transport = transport
        self.store = store
        self.linker = linker
        self.plane_ids = tuple(sorted(int(plane) for plane in plane_ids))
        self.site = site or {}
        self.analytics = analytics
        self.publish_tracks = publish_tracks
        self.delay_s = float(delay_s)
        self.max_wait_s = float(max_wait_s)
        self.linker_id = linker_id
        self._monotonic = monotonic
        self._queue: queue.Queue[tuple[Delivery, float]] = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._failure: BaseException | None = None
        self._lock = threading.Lock()
        self._clocks: dict[int, float] = {}
        self._lags: dict[int, float] = {}
        self._heard: dict[int, float] = {}
        self._started_at = 0.0
        self._sequence = 0
        self._last_watermark = -math.inf
        # plane -> [corrected_from, last time, the plane's clock when it began]
        self._correcting: dict[int, list[float]] = {}
        self._snapshot_clock = -math.inf
        self.last_activity = monotonic()
        self.reporter = ServiceReporter(
            transport, store, SITE_PLANE, [],
            places=None if analytics is None else analytics.places,
            live_interval_s=live_interval_s if analytics is not None else None,
        )

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Hold the database, resume from it, subscribe, connect and start linking.

        Raises:
            LinkerStoreError: the database is held by another linker or links another site.
            TransportError: the backbone refused or could not be reached.
        """
        self.store.hold()
        self.store.bind(self.site)
        state = self.store.linker_state()
        if state is not None:
            self.linker.set_state(state)
        if self.analytics is not None:
            self.analytics.resume(self.store)
            self.analytics.log_increments = True  # a correction takes back what was counted
        self._clocks = self.store.plane_clocks()
        self._lags = self.store.plane_lags()
        self._correcting = {int(plane): _under_way(values) for plane, values in
                            (self.store.get_meta("correcting") or {}).items()}
        if not self.store.has_snapshots():
            # The first snapshot: the state it starts from (the rows it holds are inputs).
            inbox = self.linker.get_state()["inbox"]
            self.store.commit(LinkerBatch(
                inputs=[("add", int(plane), _rows(rows)) for plane, rows in inbox.items()],
                snapshot=self._snapshot()))
        newest = self.store.snapshot_at(math.inf)
        self._snapshot_clock = -math.inf if newest is None else newest.clock
        for plane in self.plane_ids:
            self.transport.subscribe(tracks_topic(plane), self._on_delivery, qos=1)
        self.transport.connect()
        self._started_at = self._monotonic()
        self.reporter.start()
        self._announce("online")
        self._thread = threading.Thread(target=self._work, name="cblrs-linker", daemon=True)
        self._thread.start()
        logger.info("linker %s: linking planes %s (%d links), resumed at %s",
                    self.linker_id, list(self.plane_ids), len(self.linker.links),
                    None if state is None else state.get("clock"))

    def failed(self) -> BaseException | None:
        """The failure that stopped the linking thread, if any."""
        return self._failure

    def stop(self, timeout: float = 10.0) -> None:
        """Stop linking: what was taken is committed; what was not comes again next time."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self.reporter.stop(timeout=min(timeout, 5.0))

    def close(self, finish: bool = False, timeout: float = 10.0) -> None:
        """Stop (after :meth:`finish` when ``finish``), say "offline" and disconnect."""
        if finish and self._failure is None:
            self._stop.set()
            if self._thread is not None:
                self._thread.join(timeout)
            self._drain()
            self.finish()
        self.stop(timeout)
        self._announce("offline")
        self.transport.close(timeout=min(timeout, 5.0))
        if self._failure is not None:
            text = str(self._failure).strip().splitlines()
            raise LinkerFailed(f"the linker stopped: {text[0] if text else self._failure!r}") \
                from self._failure

    def finish(self) -> LinkedRows:
        """The end of every stream: decide every watched track, emit every row, end every
        track in the analytics; committed and published like a batch."""
        with self._lock:
            rows = self.linker.finish()
            writes = None
            if self.analytics is not None:
                self._count(rows)
                self.analytics.flush()
                writes = self.analytics.take_writes()
            # Nothing after the end is corrected: no snapshot to go back to.
            self.store.commit(LinkerBatch(
                rows=rows, handovers=self.linker.take_handovers(), state=self.linker.get_state(),
                counters={"rows_out": len(rows)}, analytics=writes))
            self._publish(rows, self.linker.clock)
        self.reporter.tracked([], {"events": {"finished": 1}} if writes is not None else None)
        return rows

    def stats(self) -> dict[str, Any]:
        """Counters, the clocks and what the linker holds."""
        return {
            **self.store.counters(),
            "clock": _finite(self.linker.clock),
            "plane_clocks": {str(plane): value for plane, value in sorted(self._clocks.items())},
            "watching": self.linker.watching,
            "known_tracks": self.linker.known_tracks,
            "next_global_id": self.linker.next_id,
        }

    # ------------------------------------------------------------------ deliveries
    def _on_delivery(self, delivery: Delivery) -> None:
        self._queue.put((delivery, time.time()))

    def _work(self) -> None:
        try:
            while not self._stop.is_set():
                batch = self._take(0.2)
                self._process(batch)
        except BaseException as error:  # the thread must say why it ended
            self._failure = error
            logger.error("linker %s stopped: %s", self.linker_id, error)

    def _take(self, wait_s: float) -> list[tuple[Delivery, float]]:
        try:
            batch = [self._queue.get(timeout=wait_s)]
        except queue.Empty:
            return []
        while len(batch) < 1000:
            try:
                batch.append(self._queue.get_nowait())
            except queue.Empty:
                break
        return batch

    def _drain(self) -> None:
        while True:
            batch = self._take(0.0)
            if not batch:
                return
            self._process(batch)

    def _process(self, batch: list[tuple[Delivery, float]]) -> None:
        counters: Counter[str] = Counter()
        updates: list[tuple[int, float, float, int]] = []
        taken: set[tuple[int, float]] = set()
        with self._lock:
            decoded = []
            for delivery, received_at in batch:
                counters["updates_received"] += 1
                try:
                    plane = parse_tracks_topic(delivery.topic)
                    update = decode_tracks(delivery.payload)
                    if update.plane_id != plane or plane not in self.plane_ids:
                        raise RejectedMessage(RejectReason.TOPIC_MISMATCH,
                                              f"plane {update.plane_id} on {delivery.topic}")
                    time_of = update.timestamp
                    if time_of is None and len(update.tracks):
                        time_of = float(np.max(update.tracks.timestamp))
                    if time_of is None:
                        raise RejectedMessage(RejectReason.MISSING_FIELD,
                                              "an empty update without its time")
                    if time_of > received_at + MAX_FUTURE_S:
                        raise RejectedMessage(RejectReason.IN_FUTURE,
                                              f"update time {time_of} is ahead of this host's "
                                              f"clock by {time_of - received_at:.0f} s")
                except (RejectedMessage, TopicError) as error:
                    reason = error.reason.value if isinstance(error, RejectedMessage) else (
                        "topic")
                    counters[f"rejected.{reason}"] += 1
                    logger.warning("linker %s: rejected an update on %s: %s", self.linker_id,
                                   delivery.topic, error)
                    continue
                decoded.append((plane, float(time_of), update, received_at))
            seen = self.store.seen({(plane, time_of) for plane, time_of, update, _ in decoded
                                    if update.corrected_from is None})
            seen_corrections = self.store.seen_corrections(
                {(plane, time_of, float(update.corrected_from))
                 for plane, time_of, update, _ in decoded if update.corrected_from is not None})
            now = self._monotonic()
            inputs: list[tuple[str, int, Any]] = []
            corrections: list[tuple[int, float, float]] = []
            back_to = math.inf  # the earliest corrected_from of a correction begun here
            caught_up = False  # a correction under way ended by the plane's next update
            for plane, time_of, update, received_at in decoded:
                rows = update.tracks
                if len(rows):
                    rows = rows[np.argsort(rows.timestamp, kind="stable")]
                if update.corrected_from is not None:
                    key = (plane, time_of, float(update.corrected_from))
                    if key in seen_corrections or key in corrections:
                        counters["duplicates"] += 1
                        continue
                    corrections.append(key)
                    since = float(update.corrected_from)
                    under_way = self._correcting.get(plane)
                    until = self._clocks.get(plane, -math.inf)
                    if under_way is None or under_way[0] != since or time_of <= under_way[1]:
                        # A new correction: the plane's rows after ``since`` are replaced.
                        inputs.append(("cut", plane, since))
                        back_to = min(back_to, since)
                    else:
                        until = under_way[2]
                    self._correcting[plane] = [since, time_of, until]
                    rows = rows[rows.timestamp > since] if len(rows) else rows
                    if len(rows):
                        inputs.append(("fix", plane, rows))
                        if rows.timestamp[0] <= self.linker.clock:  # linked without them
                            # Back to a snapshot from before the first row: one taken at its
                            # very time has linked that time already.
                            back_to = min(back_to, math.nextafter(float(rows.timestamp[0]),
                                                                  -math.inf))
                    self._heard[plane] = now
                    counters["corrections"] += 1
                    continue
                key = (plane, time_of)
                if key in seen or key in taken:
                    counters["duplicates"] += 1
                    continue
                taken.add(key)
                under_way = self._correcting.get(plane)
                if under_way is not None and under_way[1] < under_way[2]:
                    # The matcher has moved on: its correction is over, wherever it ended.
                    under_way[2] = under_way[1]
                    caught_up = True
                if len(rows):
                    late = rows.timestamp <= self.linker.clock
                    if late.any():  # counted, not linked (see PlaneLinker.push)
                        counters["late_rows"] += self.linker.push(plane, rows[late])
                    if not late.all():
                        inputs.append(("add", plane, rows[~late]))
                    lag = time_of - float(np.min(rows.timestamp))
                    self._lags[plane] = max(self._lags.get(plane, 0.0), lag)
                self._clocks[plane] = max(self._clocks.get(plane, -math.inf), time_of)
                self._heard[plane] = now
                counters["updates"] += 1
                counters["rows_in"] += len(rows)
                updates.append((plane, time_of, received_at, len(rows)))
            rewound = self._go_back(back_to, inputs, counters) if math.isfinite(back_to) \
                else None
            if rewound is None:
                if math.isfinite(back_to):  # older than every snapshot: not linked again
                    inputs = [item for item in inputs if item[0] == "add"]
                    for plane, _, since in corrections:  # nor are its later updates
                        self._correcting[plane] = [since, math.inf, math.inf]
                for operation, plane, rows in inputs:
                    if operation != "cut":
                        self.linker.push(plane, rows)
            watermark = self._watermark(now)
            rows_out = LinkedRows.empty()
            if watermark is not None and watermark > self._last_watermark:
                rows_out = self.linker.advance(watermark)
                self._last_watermark = watermark
            elif not updates and not counters:
                return
            writes = None
            if self.analytics is not None:
                self._count(rows_out)
                writes = self.analytics.take_writes()
            counters["rows_out"] += len(rows_out)
            handovers = self.linker.take_handovers()  # before a snapshot: it holds none
            snapshot = None
            if self.linker.clock - self._snapshot_clock >= SNAPSHOT_INTERVAL_S:
                snapshot = self._snapshot()
                self._snapshot_clock = self.linker.clock
            self.store.commit(LinkerBatch(
                updates=updates, rows=rows_out, handovers=handovers,
                state=self.linker.get_state(), clocks=dict(self._clocks), lags=dict(self._lags),
                counters=dict(counters), analytics=writes, inputs=inputs,
                corrections=corrections, rewound=rewound, snapshot=snapshot,
                correcting=dict(self._correcting) if corrections or caught_up else None))
            for delivery, _ in batch:
                delivery.ack()
            if watermark is not None and (len(rows_out) or updates or rewound is not None):
                self._publish(rows_out, watermark,
                              None if rewound is None else rewound.emitted_until)
            if batch:
                self.last_activity = self._monotonic()
        if writes is not None:
            self.reporter.tracked([], {"live": self.analytics.live(),
                                       "events": {"linked": len(writes.events)}})

    def _go_back(self, since: float, inputs: list[tuple[str, int, Any]],
                 counters: Counter[str]) -> Snapshot | None:
        """A correction from ``since``: back to the newest snapshot at or before it, then
        every plane's rows after it again (the stored ones as ``inputs`` changes them);
        None when no snapshot is that old (counted ``corrections_unlinked``)."""
        snapshot = self.store.snapshot_at(since)
        if snapshot is None:
            counters["corrections_unlinked"] += 1
            logger.warning("linker %s: a correction from %s is older than every snapshot; "
                           "not linked again", self.linker_id, since)
            return None
        planes = self.store.inputs_after(snapshot.clock)
        for operation, plane, value in inputs:
            held = planes.get(plane, Tracks.empty())
            if operation == "cut":
                planes[plane] = held[held.timestamp <= value]
            else:
                planes[plane] = Tracks.concatenate([held, value])
        self.linker.set_state({**snapshot.state, "inbox": {}})
        for plane in sorted(planes):
            rows = planes[plane]
            rows = rows[rows.timestamp > snapshot.clock]
            self.linker.push(plane, rows[np.argsort(rows.timestamp, kind="stable")])
        if self.analytics is not None and snapshot.analytics is not None:
            self.analytics.set_state(snapshot.analytics, self.store.counts_at(snapshot.log_row))
        self._last_watermark = -math.inf
        self._snapshot_clock = snapshot.clock
        counters["relinks"] += 1
        logger.info("linker %s: a correction from %s: linking again from %s", self.linker_id,
                    since, snapshot.clock)
        return snapshot

    def _snapshot(self) -> dict[str, Any]:
        return {"clock": self.linker.clock, "emitted_until": self.linker.emitted_until,
                "state": self.linker.get_state(),
                "analytics": None if self.analytics is None else self.analytics.get_state()}

    def _count(self, rows: LinkedRows) -> None:
        """Count final global rows, then move the analytics' clock to where every row before
        it has left the linker (never further: a track whose rows are still watched must not
        be ended early)."""
        assert self.analytics is not None
        if len(rows):
            # Given with its first row's time, a chunk is counted at once (it adds no lag).
            self.analytics.update(rows.tracks, float(rows.tracks.timestamp[0]))
        settled = self.linker.output_watermark
        if math.isfinite(settled):
            self.analytics.update(Tracks.empty(), settled)

    def _watermark(self, now: float) -> float | None:
        """Where every plane that counts has passed (see the module docstring), or None."""
        heard_of = [plane for plane in self.plane_ids if plane in self._clocks]
        if len(heard_of) < len(self.plane_ids) and now - self._started_at < self.max_wait_s:
            return None  # at start, every plane is waited for a while
        if not heard_of:
            return None
        live = [plane for plane in heard_of
                if now - self._heard.get(plane, self._started_at) <= self.max_wait_s]
        counted = live or heard_of
        return min(self._plane_clock(plane) - self._lags.get(plane, 0.0)
                   for plane in counted) - self.delay_s

    def _plane_clock(self, plane: int) -> float:
        """The plane's clock; while a correction of it is under way (its updates have not
        reached the clock the plane had when it began, and the plane has sent nothing else
        since), the correction's newest update time: later times would be linked without
        the corrected rows still to come, and each would send the linker back again."""
        clock = self._clocks[plane]
        under_way = self._correcting.get(plane)
        if under_way is not None and under_way[1] < under_way[2]:
            return min(clock, under_way[1])
        return clock

    def _publish(self, rows: LinkedRows, watermark: float,
                 corrected_from: float | None = None) -> None:
        if not self.publish_tracks:
            return
        for start in range(0, max(len(rows), 1), PUBLISH_ROWS):
            part = slice(start, start + PUBLISH_ROWS)
            self._sequence += 1
            try:
                self.transport.publish(site_tracks_topic(), encode_tracks(
                    rows.tracks[part], SITE_PLANE, sequence=self._sequence,
                    timestamp=float(watermark), source_plane=rows.plane_id[part],
                    source_track=rows.local_track_id[part],
                    corrected_from=None if corrected_from is None or start else corrected_from),
                    qos=1)
            except Exception as error:  # viewers miss an update; the rows are in the store
                logger.warning("linker %s: could not publish global tracks: %s",
                               self.linker_id, error)

    def _announce(self, state: Literal["online", "offline"]) -> None:
        try:
            self.transport.publish(linker_status_topic(self.linker_id),
                                   encode_status(self.linker_id, state, role="linker"),
                                   qos=1, retain=True)
        except Exception as error:
            logger.warning("linker %s: could not publish its status: %s", self.linker_id, error)


def _rows(rows: list[list[Any]]) -> Tracks:
    """A linker state's inbox rows ``[time, plane, track, frame, x, y, class]`` as tracks."""
    if not rows:
        return Tracks.empty()
    columns = list(zip(*rows, strict=True))
    return Tracks(frame=np.array(columns[3], np.int64), timestamp=np.array(columns[0], float),
                  track_id=np.array(columns[2], np.int64),
                  world_xy=np.column_stack([columns[4], columns[5]]).astype(float),
                  class_id=np.array(columns[6], np.int64))


def _under_way(values: Sequence[float]) -> list[float]:
    """A stored correction under way; one stored without the clock it must reach (an older
    file) is taken as caught up."""
    since, last, *until = (float(value) for value in values)
    return [since, last, until[0] if until else last]


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None
