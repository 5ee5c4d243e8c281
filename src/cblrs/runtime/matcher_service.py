"""The central matcher service: receive -> validate -> store -> order -> track -> publish.

One service serves one plane (the B channel of the reference colours): it subscribes to
``cblrs/<plane>/+/detections`` and ``cblrs/<plane>/+/status`` with a persistent session and
QoS 1, and acknowledges a delivery only after the message is durably in the SQLite inbox
(:class:`~cblrs.runtime.store.RuntimeStore`), so nothing acknowledged can be lost.

Per delivery:

1. **validate** with :class:`~cblrs.runtime.wire.ValidationPolicy` (schema, types, sizes,
   colour range, known camera, camera id = topic camera, capture time not too far in the
   past or future); a rejection is counted by reason and acknowledged, the service goes on;
2. **de-duplicate** by ``(camera, sequence)``: the inbox's primary key, so redeliveries are
   recognised across restarts too;
3. **order**: messages wait in a buffer grouped by equal capture timestamp. A group is
   released, in timestamp order, when every camera of the plane has delivered that timestamp
   or a later one (cameras send one message per frame, in order), or — so that a dead
   camera does not stall the plane — when the group has waited ``window_s`` *and* each
   camera still missing has been silent for ``window_s``. A camera that is still sending
   older frames (e.g. a slower replay) is waited for, so an ordinary replay has no late
   messages; a camera that says "offline" is not waited for. The window clock stops while
   the service is disconnected from the broker, so an outage does not expire groups whose
   remaining messages are queued at the broker. A message at or before the last released
   timestamp is ``late``: stored, counted, not tracked;
4. **track**: the group goes to the matcher (``update(timestamp, messages)``, messages in
   camera order) and one transaction stores its track rows, marks its inbox rows processed
   and saves the matcher state (``get_state()``); the rows are published on
   ``cblrs/<plane>/tracks``. Groups released together (a backlog) share one transaction.

Two threads share the work: a *receiver* (steps 1-3: validate, store, acknowledge, buffer)
and a *tracker* (step 4), so an acknowledgement never waits for the tracker and a burst of
messages is stored while the previous group is being tracked. A group leaves the buffer and
the "last released timestamp" advances in one step under a lock, so a message is either in
its group or counted late, never both.

A restarted service resumes from what SQLite holds: the matcher state and the last released
timestamp of the last committed group, the unprocessed inbox rows (back into the buffer) and
the de-duplication set. Messages that were received but not yet stored were never
acknowledged, so the broker delivers them again.
"""

from __future__ import annotations

import functools
import logging
import math
import queue
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from cblrs.detections import CameraMessage, Tracks
from cblrs.runtime.store import LATE, PENDING, RuntimeStore
from cblrs.runtime.topics import (
    TopicError,
    detections_filter,
    parse_detections_topic,
    parse_status_topic,
    status_filter,
    tracks_topic,
    validate_camera_id,
)
from cblrs.runtime.wire import (
    RejectedMessage,
    ValidationPolicy,
    decode_status,
    encode_tracks,
)

logger = logging.getLogger(__name__)

_BACKLOG_GROUPS = 3
"""Buffered groups beyond which the receiver lets the tracker catch up before storing more."""

COUNTER_NAMES = ("received", "accepted", "duplicates", "late", "processed", "groups", "tracks")
"""Counters every summary shows (rejections add ``rejected.<reason>``)."""


@dataclass
class _Group:
    messages: dict[str, CameraMessage]
    first_arrival: float  # service clock


class ServiceClock:
    """Monotonic seconds that stand still while ``connected()`` is False.

    Args:
        connected: whether the service is currently connected to its broker.
        monotonic: the underlying clock.
    """

    def __init__(
        self, connected: Callable[[], bool], monotonic: Callable[[], float] = time.monotonic
    ):
        self._connected = connected
        self._monotonic = monotonic
        self._paused = 0.0
        self._down_since: float | None = None
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            now = self._monotonic()
            if not self._connected():
                if self._down_since is None:
                    self._down_since = now
                return now - self._paused - (now - self._down_since)
            if self._down_since is not None:
                self._paused += now - self._down_since
                self._down_since = None
            return now - self._paused


class MatcherService:
    """The matcher of one plane, fed through a transport, persisted in a store.

    Args:
        transport: the :class:`~cblrs.runtime.transport.Transport` (persistent session).
        store: the SQLite store of this plane's matcher.
        matcher: a :class:`~cblrs.matching.Matcher` built for ``camera_ids``.
        plane_id: the plane served.
        camera_ids: the plane's cameras; ``Tracks.camera_id`` indexes this list.
        policy: validation limits (its ``known_cameras`` is set to ``camera_ids``).
        window_s: ordering window, seconds (see the module docstring).
        publish_tracks: publish each group's rows on ``cblrs/<plane>/tracks``.
        max_buffered_groups: release the oldest group regardless once more are waiting.
        batch_size: deliveries stored per inbox transaction, at most.
        groups_per_commit: released groups tracked per store transaction, at most.
        settings: extra identity stored with the database (matcher name and options); a
            reopened database must have been written with the same.
        observer: optional object with ``on_stored(messages, wall_time)`` and/or
            ``on_group(timestamp, messages, tracks, wall_time)`` (benchmarks, viewers).
        wall_clock: seconds since the Unix epoch (for staleness checks and receipt times).
    """

    def __init__(
        self,
        transport: Any,
        store: RuntimeStore,
        matcher: Any,
        plane_id: int,
        camera_ids: Sequence[str],
        *,
        policy: ValidationPolicy | None = None,
        window_s: float = 2.0,
        publish_tracks: bool = True,
        max_buffered_groups: int = 10_000,
        batch_size: int = 500,
        groups_per_commit: int = 50,
        settings: dict[str, Any] | None = None,
        observer: Any = None,
        wall_clock: Callable[[], float] = time.time,
    ):
        if window_s < 0 or not math.isfinite(window_s):
            raise ValueError(f"window must be a finite number >= 0, got {window_s}.")
        self.camera_ids = [validate_camera_id(name) for name in camera_ids]
        if not self.camera_ids or len(set(self.camera_ids)) != len(self.camera_ids):
            raise ValueError(f"camera ids must be distinct and non-empty, got {camera_ids}.")
        self.transport = transport
        self.store = store
        self.matcher = matcher
        self.plane_id = int(plane_id)
        base = policy or ValidationPolicy()
        self.policy = ValidationPolicy(
            known_cameras=frozenset(self.camera_ids),
            bits=base.bits,
            max_age_s=base.max_age_s,
            max_future_s=base.max_future_s,
            max_bytes=base.max_bytes,
        )
        self.window_s = float(window_s)
        self.publish_tracks = publish_tracks
        self.max_buffered_groups = int(max_buffered_groups)
        self.batch_size = int(batch_size)
        self.groups_per_commit = max(1, int(groups_per_commit))
        self.observer = observer
        self._wall_clock = wall_clock
        self.clock = ServiceClock(lambda: bool(getattr(transport, "connected", True)))
        self._camera_order = {name: index for index, name in enumerate(self.camera_ids)}
        self._settings = {"plane_id": self.plane_id, "camera_ids": self.camera_ids}
        self._settings.update(settings or {})

        self._inbox: queue.Queue = queue.Queue()
        self._groups: dict[float, _Group] = {}
        self._released: float | None = None
        self._latest: dict[str, float] = {}
        self._last_heard: dict[str, float] = {}
        self._offline: dict[str, bool] = dict.fromkeys(self.camera_ids, False)
        self._final_offline: dict[str, bool] = dict.fromkeys(self.camera_ids, False)
        self._offline_at: dict[str, float | None] = dict.fromkeys(self.camera_ids, None)
        self._started_at = wall_clock()
        self._active_this_run: set[str] = set()
        self._last_delivery = 0.0
        self._silence_origin: float | None = None
        self._updates = 0
        self._run_counters: Counter[str] = Counter()
        self._stop = threading.Event()
        self._flush_requested = threading.Event()
        self._wake = threading.Event()
        self._tracked = threading.Event()
        self._received_all = threading.Event()
        self._state_lock = threading.RLock()
        self._processing = 0
        self._worker: threading.Thread | None = None
        self._tracker: threading.Thread | None = None
        self._failure: BaseException | None = None
        self._lock = threading.Lock()
        self._started = False

    # -- lifecycle -------------------------------------------------------------------------

    def start(self, connect: bool = True) -> None:
        """Resume from the store, subscribe and start the worker thread.

        Args:
            connect: also connect the transport (else the caller connects it afterwards).
        """
        if self._started:
            return
        self.store.bind(self._settings)
        self._started_at = self._wall_clock()
        self._recover()
        self._last_delivery = self.clock()
        self._worker = threading.Thread(
            target=self._work, name=f"cblrs-matcher-{self.plane_id}", daemon=True
        )
        self._tracker = threading.Thread(
            target=self._track, name=f"cblrs-tracker-{self.plane_id}", daemon=True
        )
        self._worker.start()
        self._tracker.start()
        self.transport.subscribe(status_filter(self.plane_id), self._on_status, qos=1)
        self.transport.subscribe(detections_filter(self.plane_id), self._on_detections, qos=1)
        if connect:
            self.transport.connect()
        self._started = True

    def stop(self, flush: bool = False, timeout: float = 30.0) -> None:
        """Stop the worker; with ``flush``, first store and track everything received.

        Without ``flush`` waiting groups stay pending in the store and a restarted service
        processes them.
        """
        if flush:
            self._flush_requested.set()
        self._stop.set()
        deadline = time.monotonic() + timeout
        for thread in (self._worker, self._tracker):
            if thread is not None:
                thread.join(max(0.0, deadline - time.monotonic()))
                if thread.is_alive():
                    logger.warning("matcher thread %s did not stop within %.0f s",
                                   thread.name, timeout)
        if self._failure is not None:
            raise RuntimeError("the matcher service worker failed") from self._failure

    def close(self, flush: bool = False) -> None:
        """:meth:`stop`, then close the transport (the store stays open for the caller)."""
        try:
            self.stop(flush=flush)
        finally:
            self.transport.close()

    def _recover(self) -> None:
        state = self.store.matcher_state()
        if state is not None:
            self.matcher.set_state(state)
        self._released = self.store.released_timestamp()
        for camera, summary in self.store.inbox_summary().items():
            if camera in self._offline:
                self._latest[camera] = summary["max_timestamp"]
        now = self.clock()
        pending = self.store.messages(PENDING)
        for stored in pending:
            self._buffer(stored.message, now)
        if state is not None or pending:
            logger.info(
                "plane %d: resumed at %s with %d pending messages",
                self.plane_id, self._released, len(pending),
            )

    # -- transport callbacks (transport thread) -----------------------------------------

    def _on_detections(self, delivery: Any) -> None:
        self._inbox.put(("detections", delivery, self._wall_clock()))

    def _on_status(self, delivery: Any) -> None:
        self._inbox.put(("status", delivery, self._wall_clock()))

    # -- worker thread -------------------------------------------------------------------

    def _work(self) -> None:
        """Receiver thread: store and acknowledge deliveries, buffer them for the tracker."""
        try:
            while True:
                if len(self._groups) > _BACKLOG_GROUPS and not self._stop.is_set():
                    # The tracker is behind: let deliveries pile up while it works, so they
                    # are stored in one large transaction rather than many small ones and
                    # the tracker gets the interpreter (a steady stream never waits here).
                    self._tracked.wait(0.05)
                    self._tracked.clear()
                batch = []
                try:
                    batch.append(self._inbox.get(timeout=0.2))
                    while len(batch) < self.batch_size:
                        batch.append(self._inbox.get_nowait())
                except queue.Empty:
                    pass
                if batch:
                    self._handle(batch)
                    self._wake.set()
                # Stopping: finish the current batch; with a flush, also what is queued.
                # Anything left is unacknowledged, so the broker delivers it again later.
                if self._stop.is_set() and (
                    self._inbox.empty() or not self._flush_requested.is_set()
                ):
                    break
        except BaseException as error:  # surfaced by stop()
            logger.exception("matcher service receiver failed")
            self._failure = error
        finally:
            self._received_all.set()
            self._wake.set()

    def _track(self) -> None:
        """Tracker thread: release ready groups, track them, commit, publish."""
        try:
            while not self._received_all.is_set():
                self._wake.wait(0.05 if self._groups else 0.2)
                self._wake.clear()
                self._release_ready()
            if self._failure is None:
                self._release_ready()
                if self._flush_requested.is_set():
                    self._release_ready(force=True)
        except BaseException as error:  # surfaced by stop()
            logger.exception("matcher service tracker failed")
            self._failure = error
            self._stop.set()

    def _handle(self, batch: list[tuple[str, Any, float]]) -> None:
        # Late marking, storing and buffering happen as one step against the tracker's
        # release of groups (see the module docstring).
        with self._state_lock:
            self._handle_locked(batch)

    def _handle_locked(self, batch: list[tuple[str, Any, float]]) -> None:
        now = self.clock()
        counters: Counter[str] = Counter()
        accepted: list[tuple[CameraMessage, str, float]] = []
        acknowledge = []
        for kind, delivery, received_at in batch:
            acknowledge.append(delivery)
            if kind == "status":
                self._status(delivery, now)
                continue
            self._last_delivery = now
            counters["received"] += 1
            try:
                plane_id, camera = _parse_topic(delivery.topic)
                message, _ = self.policy.decode_with_plane(
                    delivery.payload, topic_camera=camera, now=received_at, topic_plane=plane_id
                )
            except TopicError:
                counters["rejected.bad_topic"] += 1
                continue
            except RejectedMessage as error:
                counters[f"rejected.{error.reason.value}"] += 1
                logger.debug("rejected on %s: %s", delivery.topic, error)
                continue
            late = self._released is not None and message.timestamp <= self._released
            accepted.append((message, LATE if late else PENDING, received_at))
        inserted = self.store.insert_messages(accepted, counters)
        # Acknowledge only now: everything above is durably stored (or rejected on purpose).
        for delivery in acknowledge:
            delivery.ack()
        stored = []
        for (message, status, _), new in zip(accepted, inserted, strict=True):
            if not new:
                continue
            stored.append(message)
            self._active_this_run.add(message.camera_id)
            self._last_heard[message.camera_id] = now
            if self._silence_origin is None:
                self._silence_origin = now
            self._latest[message.camera_id] = max(
                self._latest.get(message.camera_id, -math.inf), message.timestamp
            )
            if status == PENDING:
                self._buffer(message, now)
        self._run_counters.update(counters)
        if self.observer is not None and hasattr(self.observer, "on_stored") and stored:
            self.observer.on_stored(stored, self._wall_clock())

    def _status(self, delivery: Any, now: float) -> None:
        try:
            plane_id, camera = parse_status_topic(delivery.topic)
            status = decode_status(delivery.payload)
        except (TopicError, RejectedMessage) as error:
            logger.debug("ignored status on %s: %s", delivery.topic, error)
            return
        if camera not in self._offline or plane_id != self.plane_id:
            return
        if status.state == "online":
            self._offline[camera] = self._final_offline[camera] = False
            self._offline_at[camera] = None
            self._active_this_run.add(camera)
            self._last_heard[camera] = now
            if self._silence_origin is None:
                self._silence_origin = now
        elif status.timestamp is None:
            # A last will (no timestamp): the connection dropped — a crash, or a broker
            # restart. It does not say the stream ended, so ordering keeps waiting for the
            # camera's messages (bounded by the silence window).
            pass
        else:
            # The camera's own "offline" at the end of its stream: nothing more will come.
            self._final_offline[camera] = True
            self._offline_at[camera] = status.timestamp
            # A retained one older than this service is history (the end of an earlier
            # replay): the camera may be about to start again, so ordering still waits.
            stale = bool(getattr(delivery, "retain", False)) and (
                status.timestamp < self._started_at
            )
            if not stale:
                self._offline[camera] = True
        logger.info("plane %d: camera %s is %s", self.plane_id, camera, status.state)

    def _buffer(self, message: CameraMessage, now: float) -> None:
        group = self._groups.get(message.timestamp)
        if group is None:
            group = self._groups[message.timestamp] = _Group({}, now)
        group.messages[message.camera_id] = message

    def _ready(self, timestamp: float, group: _Group, now: float) -> bool:
        missing = [
            camera
            for camera in self.camera_ids
            if self._latest.get(camera, -math.inf) < timestamp and not self._offline[camera]
        ]
        if not missing:
            return True
        if now - group.first_arrival < self.window_s:
            return False
        origin = self._silence_origin if self._silence_origin is not None else now
        return all(
            now - self._last_heard.get(camera, origin) >= self.window_s for camera in missing
        )

    def _release_ready(self, force: bool = False) -> None:
        while True:
            with self._state_lock:
                batch: list[tuple[float, _Group]] = []
                while self._groups and len(batch) < self.groups_per_commit:
                    now = self.clock()
                    timestamp = min(self._groups)
                    group = self._groups[timestamp]
                    if not (
                        force
                        or len(self._groups) > self.max_buffered_groups
                        or self._ready(timestamp, group, now)
                    ):
                        break
                    del self._groups[timestamp]
                    batch.append((timestamp, group))
                if not batch:
                    return
                # From now on a message at or before these timestamps is late; the store
                # records the same timestamp when the groups are committed.
                self._released = batch[-1][0]
                self._processing += 1
            try:
                self._process(batch)
            finally:
                with self._state_lock:
                    self._processing -= 1
                self._tracked.set()

    def _process(self, batch: list[tuple[float, _Group]]) -> None:
        """Track released groups in time order and commit them in one transaction."""
        results = []
        for timestamp, group in batch:
            messages = sorted(
                group.messages.values(), key=lambda m: self._camera_order[m.camera_id]
            )
            results.append((timestamp, messages, self.matcher.update(timestamp, messages)))
        keys = [(m.camera_id, m.sequence) for _, messages, _ in results for m in messages]
        tracks = Tracks.concatenate([tracks for _, _, tracks in results])
        counters = {"processed": len(keys), "groups": len(results), "tracks": len(tracks)}
        # One snapshot after the last group: the file holds all of these groups or none.
        self.store.commit_group(keys, tracks, self.matcher.get_state(), batch[-1][0], counters)
        with self._state_lock:
            self._run_counters.update(counters)
        for timestamp, messages, group_tracks in results:
            self._updates += 1
            if self.publish_tracks:
                try:
                    payload = encode_tracks(
                        group_tracks, self.plane_id, sequence=self._updates,
                        cameras=self.camera_ids,
                    )
                    self.transport.publish(tracks_topic(self.plane_id), payload, qos=1)
                except Exception:  # a viewer feed must never stop the matcher
                    logger.exception("could not publish tracks of %s", timestamp)
            if self.observer is not None and hasattr(self.observer, "on_group"):
                self.observer.on_group(timestamp, messages, group_tracks, self._wall_clock())

    # -- queries (any thread) --------------------------------------------------------------

    def idle_seconds(self) -> float:
        """Seconds (service clock) since the last detections delivery."""
        return self.clock() - self._last_delivery

    def buffered(self) -> int:
        """Messages waiting in the ordering buffer."""
        with self._state_lock:
            return sum(len(group.messages) for group in self._groups.values())

    def cameras_done(self) -> bool:
        """Whether every camera has ended its stream with its own "offline" status.

        A camera counts when it went offline after being online or sending during this
        run, or when its "offline" is newer than everything the store holds from it (a
        replay that finished while this service was down). A last will (a dropped
        connection) does not count.
        """
        summary = None
        for camera in self.camera_ids:
            if not self._final_offline[camera]:
                return False
            if camera in self._active_this_run:
                continue
            if summary is None:
                summary = self.store.inbox_summary()
            offline_at = self._offline_at[camera]
            if camera not in summary or offline_at is None:
                return False
            if offline_at < summary[camera]["max_received_at"]:
                return False
        return True

    def drained(self) -> bool:
        """Nothing waiting: no undelivered batch, no buffered group, no group being tracked."""
        with self._state_lock:
            return self._inbox.empty() and not self._groups and not self._processing

    def failed(self) -> bool:
        return self._failure is not None

    def stats(self) -> dict[str, Any]:
        """Totals from the store plus the live buffer state."""
        summary = self.store.summary()
        counters = summary["counters"]
        rejected = {
            name.split(".", 1)[1]: value
            for name, value in counters.items()
            if name.startswith("rejected.")
        }
        totals = {name: counters.get(name, 0) for name in COUNTER_NAMES}
        totals["rejected"] = sum(rejected.values())
        return {
            "plane_id": self.plane_id,
            "cameras": len(self.camera_ids),
            **totals,
            "rejected_by_reason": rejected,
            "buffered_messages": self.buffered(),
            "buffered_groups": len(self._groups),
            "inbox": summary["inbox"],
            "track_ids": summary["track_ids"],
            "released_timestamp": self._released,
            "offline_cameras": sorted(c for c, off in self._offline.items() if off),
        }


@functools.lru_cache(maxsize=4096)
def _parse_topic(topic: str) -> tuple[int, str]:
    """:func:`parse_detections_topic`, cached: a plane has few cameras, hence few topics."""
    return parse_detections_topic(topic)


def stored_tracks(store: RuntimeStore) -> Tracks:
    """All track rows of a store (convenience for callers holding only the service)."""
    return store.tracks()


def inbox_keys(store: RuntimeStore) -> dict[str, set[int]]:
    """``camera -> {sequence}`` of every message in a store's inbox."""
    keys: dict[str, set[int]] = defaultdict(set)
    for stored in store.messages():
        keys[stored.message.camera_id].add(stored.message.sequence)
    return dict(keys)
