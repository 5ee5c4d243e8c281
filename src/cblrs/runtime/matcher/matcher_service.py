"""The central matcher service: receive -> validate -> store -> order -> track -> publish.

One service serves one plane (the B channel of the reference colours): it subscribes to
``cblrs/<plane>/+/detections`` and ``cblrs/<plane>/+/status`` with a persistent session and
QoS 1, and acknowledges a delivery only after the message is durably in the SQLite inbox
(:class:`~cblrs.runtime.matcher.store.RuntimeStore`), so nothing acknowledged can be lost.

Per delivery:

1. **validate** with :class:`~cblrs.runtime.wire.ValidationPolicy` (schema, types, sizes,
   colour range, known camera, camera id = topic camera, capture time not too far in the
   past or future); a rejection is counted by reason and acknowledged, the service goes on;
2. **de-duplicate** by ``(camera, sequence)``: the inbox's primary key, so redeliveries are
   recognised across restarts too;
3. **order** (:class:`~cblrs.runtime.matcher.ordering.Orderer`): messages wait in a buffer and are
   released in windows of nearby capture times (cameras need not share a clock, a frame
   rate nor capture instants) once no camera can still add to them: every camera has moved
   past the window, is in it, is not due to capture again before its end, or said
   "offline"; a dead camera is given up after ``window_s`` of silence. The window clock
   stops while the service is disconnected from the broker (on NATS, also until its
   consumer has delivered what the stream holds again), so an outage does not expire
   windows whose remaining messages are queued at the broker. A message at or before the
   last released window's timestamp is ``late``: stored and counted, then tracked by
   re-tracking once no late message has come for ``retrack.delay_s``: the tracker process
   goes back to a snapshot before it, tracks everything since again and publishes the
   corrected rows (:mod:`cblrs.runtime.matcher.retrack`; without snapshots, or older than the
   oldest, it stays untracked);
4. **track**: the window goes to the matcher (``update(timestamp, messages)``, messages in
   time and camera order; the fusion tracker fuses each at its own clock-corrected capture
   time) and one transaction stores the track rows it returns, marks the window's inbox rows
   processed and saves the matcher state (``get_state()``, messages it still holds
   included); the rows are published on ``cblrs/<plane>/tracks``. Windows released together
   (a backlog) share one transaction. Stopping with ``flush`` fuses what the matcher holds.

Steps 1-3 run in the service's process: a *receiver* thread validates, stores, acknowledges
and buffers the deliveries the transport's thread queues, in batches of what has arrived (one
inbox transaction each), and a *releaser* thread sends released groups to step 4. Step 4 runs
in a separate *tracker process* (:mod:`cblrs.runtime.matcher.tracker_process`), which writes to the
same SQLite file (the two take turns through a lock on a file next to it); a *collector*
thread publishes its track updates. So receiving and tracking use two cores, an
acknowledgement never waits for the tracker, and messages are stored while earlier groups are
being tracked. A group leaves the buffer and the "last released timestamp" advances in one
step under a lock, so a message is either in its group or counted late, never both. If the
tracker process fails or dies, the service stops (:meth:`MatcherService.failed`; ``stop``
raises); a restarted service resumes from the store.

A restarted service resumes from what SQLite holds: the matcher state and the last released
timestamp of the last committed group, the unprocessed inbox rows (back into the buffer) and
the de-duplication set. Messages that were received but not yet stored were never
acknowledged, so the broker delivers them again.

Lifecycle (this module's share of "nothing acknowledged is lost"):

* the service holds its database exclusively (:meth:`RuntimeStore.hold`) and its plane
  through a lease on the broker (:mod:`cblrs.runtime.matcher.lease`); it acknowledges nothing before
  it holds both, and after a reconnection nothing before the lease is confirmed again; a
  second matcher of the plane is refused, a matcher that loses its lease stops;
* every inbox commit checks the database file is still the one opened; if it was deleted
  or replaced the service fails and acknowledges nothing more;
* after each inbox commit the stored (and rejected) sequences are confirmed to their
  cameras (:mod:`cblrs.runtime.matcher.confirmations`), which keep them in their spools until then;
* the service announces itself on ``cblrs/<plane>/matchers/<id>/status``: "online" (with
  whether the broker kept its session) after it holds the lease and after every
  reconnection, a timestamped "offline" when it stops;
* rejections are counted by reason and logged at most once per reason every
  ``log_interval_s`` seconds.

It stays one module because :class:`MatcherService` is the one place where the numbered steps
meet in a single transaction per delivery (store, track, analytics, confirmations); the steps
themselves live in their own modules (wire, store, ordering, the matchers, online analytics).
"""

from __future__ import annotations

import functools
import logging
import math
import multiprocessing
import threading
import time
from collections import Counter, defaultdict, deque
from collections.abc import Callable, Sequence
from typing import Any

from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.matching.fusion import clock_report
from cblrs.runtime.matcher.confirmations import ConfirmationBuffer, peek_sequence
from cblrs.runtime.matcher.lease import PlaneLease
from cblrs.runtime.matcher.metrics import ServiceMetrics
from cblrs.runtime.matcher.ordering import Orderer
from cblrs.runtime.matcher.retention import RetentionPolicy, apply_retention
from cblrs.runtime.matcher.retrack import RetrackPolicy
from cblrs.runtime.matcher.store import LATE, PENDING, InboxEntry, RuntimeStore
from cblrs.runtime.matcher.tracker_process import Batch, TrackerProcess, TrackerProcessError
from cblrs.runtime.outputs.analytics_service import ServiceReporter
from cblrs.runtime.transport.rate_limited import RateLimitedLog
from cblrs.runtime.transport.topics import (
    TopicError,
    detections_filter,
    matcher_status_topic,
    parse_detections_topic,
    parse_status_topic,
    status_filter,
    tracks_topic,
    validate_camera_id,
)
from cblrs.runtime.wire import RejectedMessage, ValidationPolicy, decode_status, encode_status

logger = logging.getLogger(__name__)

COUNTER_NAMES = ("received", "accepted", "duplicates", "conflicts", "late", "processed",
                 "groups", "tracks", "retracks", "retracked", "late_tracked", "late_untracked")
"""Counters every summary shows (rejections add ``rejected.<reason>``)."""


class LeaseLost(RuntimeError):
    """Another matcher instance took the plane: this one stopped acknowledging."""


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
        transport: the :class:`~cblrs.runtime.transport.protocol.Transport` (persistent session).
        store: the SQLite store of this plane's matcher (the tracker process opens it too).
        matcher: a :class:`~cblrs.matching.Matcher` built for ``camera_ids``; it is pickled
            into the tracker process, which resumes it from the store's state (this object
            itself is not updated).
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
        observer: optional object with ``on_stored(entries, wall_time)``,
            ``on_released(timestamps, wall_time)`` and/or ``on_group(timestamp, entries,
            tracks, wall_time)`` (benchmarks, viewers), called once the entries
            (:class:`~cblrs.runtime.matcher.store.InboxEntry`) are stored and acknowledged,
            once groups leave the ordering buffer for the tracker process (their
            timestamps), and once a group's tracks are committed and handed to the
            transport; ``wall_time`` is the wall clock then.
        wall_clock: seconds since the Unix epoch (for staleness checks and receipt times).
        lease: hold the plane through a lease on the broker (see the module docstring);
            None (default): unless the transport holds a lease of its own (the NATS
            transport's ``lease``).
        allow_other_database: start even if the plane was last served from another
            database (``cblrs matcher --new-db``).
        confirm_interval_s: how often stored sequences are confirmed to the cameras.
        log_interval_s: at most one log line per rejection reason this often.
        retention: how much history the database keeps (:mod:`cblrs.runtime.matcher.retention`;
            default: 24 h or 4 GiB, never anything not yet tracked); None keeps everything.
        analytics: the plane's :class:`~cblrs.runtime.outputs.online_analytics.OnlineAnalytics`:
            counted in the tracker process with each group, committed with it, events
            published from the store (:mod:`cblrs.runtime.outputs.analytics_service`); None: none.
        metrics: :class:`~cblrs.runtime.matcher.metrics.ServiceMetrics` to feed, or None.
        live_interval_s: seconds between live summaries on ``cblrs/<plane>/live`` (counts,
            occupancy, camera health); None publishes none.
        retrack: snapshots and re-tracking of late messages (:mod:`cblrs.runtime.matcher.retrack`);
            None: late messages stay untracked.
        alerts: the site's ``alerts:`` (:class:`cblrs.alerts.AlertsModel`): evaluated,
            committed, published on ``cblrs/<plane>/alerts`` and posted to its webhooks by
            :class:`~cblrs.runtime.outputs.alert_service.AlertService`; None (or no rules): none.
        alert_senders: webhook name -> :class:`cblrs.alerts.WebhookSender` (their secrets
            read: :func:`cblrs.runtime.outputs.alert_service.make_senders`).
        camera_fps: the cameras' frame rate (the fastest of them), if known: ordering
            predicts a camera's next frame from it until the camera's own period is measured
            (its first four frames), so its first frames do not wait for their successors;
            a camera found faster is predicted from its intervals at once. None: they wait.
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
        lease: bool | None = None,
        allow_other_database: bool = False,
        confirm_interval_s: float = 0.25,
        log_interval_s: float = 10.0,
        retention: RetentionPolicy | None = RetentionPolicy(),  # noqa: B008 (frozen)
        analytics: Any = None,
        metrics: ServiceMetrics | None = None,
        live_interval_s: float | None = 1.0,
        retrack: RetrackPolicy | None = RetrackPolicy(),  # noqa: B008 (frozen)
        alerts: Any = None,
        alert_senders: dict[str, Any] | None = None,
        camera_fps: float | None = None,
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
        if camera_fps is not None and not (camera_fps > 0 and math.isfinite(camera_fps)):
            raise ValueError(f"camera fps must be a finite number > 0, got {camera_fps}.")
        self.camera_fps = camera_fps
        self._orderer = Orderer(
            self.camera_ids, timeout_s=self.window_s, max_buffered_groups=self.max_buffered_groups,
            assumed_period_s=None if camera_fps is None else 1.0 / camera_fps)
        self.batch_size = int(batch_size)
        self.groups_per_commit = max(1, int(groups_per_commit))
        self.observer = observer
        self._wall_clock = wall_clock
        # The silence timeout counts only while messages can arrive: connected, and (NATS)
        # the plane's consumer has delivered what its stream holds.
        self.clock = ServiceClock(lambda: bool(getattr(
            transport, "caught_up", getattr(transport, "connected", True))))
        self._settings = {"plane_id": self.plane_id, "camera_ids": self.camera_ids}
        self._settings.update(settings or {})

        self._inbox: deque[tuple[str, Any, float]] = deque()
        self._arrived = threading.Event()
        self._offline: dict[str, bool] = dict.fromkeys(self.camera_ids, False)
        self._final_offline: dict[str, bool] = dict.fromkeys(self.camera_ids, False)
        self._offline_at: dict[str, float | None] = dict.fromkeys(self.camera_ids, None)
        self._started_at = wall_clock()
        self._active_this_run: set[str] = set()
        self._last_delivery = 0.0
        self._stop = threading.Event()
        self._flush_requested = threading.Event()
        self._wake = threading.Event()
        self._received_all = threading.Event()
        self._state_lock = threading.RLock()
        self._inflight: deque[Batch] = deque()  # sent to the tracker process, not answered
        self._tracker: TrackerProcess | None = None
        self._threads: list[threading.Thread] = []
        self._failure: BaseException | None = None
        self._started = False
        self.matcher_id = str(getattr(transport, "client_id", f"matcher{self.plane_id}"))
        self._use_lease = (getattr(transport, "lease", None) is None) if lease is None else lease
        self._allow_other_database = allow_other_database
        self._lease: PlaneLease | None = None
        self._receiving = threading.Event()
        self._connections = 0
        self._session_present = False
        self._confirmations = ConfirmationBuffer(self.plane_id, self.matcher_id)
        self.confirm_interval_s = float(confirm_interval_s)
        self._last_confirmation = 0.0
        self._rejections = RateLimitedLog(logger, log_interval_s)
        self._retained_warned: set[str] = set()
        self.retention = retention
        self.retrack = retrack
        self._late_at: float | None = None  # service clock of the last late message waiting
        self._retracks_inflight = 0
        self.analytics = analytics
        self.reporter = ServiceReporter(
            transport, store, self.plane_id, self.camera_ids,
            places=None if analytics is None else analytics.places, metrics=metrics,
            live_interval_s=live_interval_s,
        )
        self.alerts: Any = None  # an AlertService when the site has alert rules
        if alerts is not None and alerts.rules:
            # lazy: the alerts' rule models (pydantic) cost a matcher without rules about
            # 0.3 CPU-s to import, paid at every start
            from cblrs.runtime.outputs.alert_service import AlertService

            # The opening hours that gate counting gate the places' alerts too.
            calendar = None if analytics is None else analytics.engine.config.calendar
            self.alerts = AlertService(transport, store, self.plane_id, self.camera_ids,
                                       alerts, alert_senders or {}, self.reporter, self.lag,
                                       calendar=calendar)

    # -- lifecycle -------------------------------------------------------------------------

    def start(self, connect: bool = True) -> None:
        """Resume from the store, start the tracker process and the threads, subscribe.

        Args:
            connect: also connect the transport (else the caller connects it afterwards).
        """
        if self._started:
            return
        self.store.hold()
        self.store.bind(self._settings)
        if self.analytics is not None:
            # Here, not only in the tracker process: a state counted with other places or
            # settings is refused with one sentence before anything starts.
            self.analytics.resume(self.store)
        add_hook = getattr(self.transport, "add_connect_hook", None)
        if add_hook is not None:
            add_hook(self._on_connected)
        if self._use_lease:
            # Before anything is acknowledged: deliveries wait in the inbox meanwhile.
            self._lease = PlaneLease(
                self.transport, self.plane_id, self.matcher_id, self.store.database_id(),
                allow_other_database=self._allow_other_database,
            )
            self._lease.register()
        self.transport.subscribe(status_filter(self.plane_id), self._on_status, qos=1)
        self.transport.subscribe(detections_filter(self.plane_id), self._on_detections, qos=1)
        if connect:
            self.transport.connect()
        if self._lease is not None:
            self._lease.acquire()
        tracker = self.store.claim()  # before reading where to resume
        self._started_at = self._wall_clock()
        self._recover()
        self._last_delivery = self.clock()
        context = _process_context()
        self._tracker = TrackerProcess(
            context, self.matcher, self.store.share(), tracker, self.plane_id,
            self.camera_ids, self.publish_tracks, self.analytics, self.retrack,
        )
        self._threads = [
            threading.Thread(target=target, name=f"cblrs-{role}-{self.plane_id}", daemon=True)
            for role, target in (("receiver", self._work), ("releaser", self._release),
                                 ("collector", self._collect), ("retention", self._retain))
        ]
        for thread in self._threads:
            thread.start()
        if self._lease is not None:
            self._lease.start(self._lease_lost, self._lease_confirmed)
        self.reporter.start()
        if self.alerts is not None:
            self.alerts.start()
        self._receiving.set()
        self._announce("online")
        self._started = True
        logger.info("plane %d: matcher %s serving cameras %s", self.plane_id, self.matcher_id,
                    ", ".join(self.camera_ids))

    def stop(self, flush: bool = False, timeout: float = 30.0) -> None:
        """Stop the threads and the tracker process; with ``flush``, first store and track
        everything received.

        Without ``flush`` waiting groups stay pending in the store and a restarted service
        processes them; so do groups sent to the tracker process and not yet committed (it
        abandons them), so a backlog does not delay the stop.

        Raises:
            RuntimeError: a thread or the tracker process failed (the cause is chained).
        """
        if flush:
            self._flush_requested.set()
        elif self._tracker is not None:
            # What is released but not committed stays pending: a backlog does not hold the
            # stop (a restart tracks it).
            self._tracker.abandon()
        self._stop.set()
        self._arrived.set()
        self._wake.set()
        deadline = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
            if thread.is_alive():
                logger.warning("matcher thread %s did not stop within %.0f s",
                               thread.name, timeout)
        if self._tracker is not None:
            self._tracker.close(max(0.0, deadline - time.monotonic()))
        if self.alerts is not None:
            self.alerts.stop(max(1.0, deadline - time.monotonic()))
        self.reporter.stop(max(1.0, deadline - time.monotonic()))
        self._send_confirmations(force=True)
        if self._lease is not None:
            self._lease.release()  # nothing more is acknowledged: a restart may claim at once
        self.store.release_hold()
        if self._failure is not None:
            raise RuntimeError("the matcher service failed") from self._failure

    def close(self, flush: bool = False) -> None:
        """:meth:`stop`, then release the lease, say "offline" and close the transport (the
        store stays open for the caller)."""
        try:
            self.stop(flush=flush)
        finally:
            try:
                if self._started and getattr(self.transport, "connected", True):
                    self._announce("offline")
                    clear_will = getattr(self.transport, "clear_will", None)
                    if clear_will is not None:
                        clear_will()
            finally:
                # Without a broker nothing more is acknowledged: waiting would only hold the
                # stop (what is not, a restart sends again).
                self.transport.close(timeout=5.0 if getattr(self.transport, "connected", True)
                                     else 1.0)

    def _announce(self, state: str) -> None:
        """The matcher's retained, timestamped status (cameras watch it)."""
        try:
            self.transport.publish(
                matcher_status_topic(self.plane_id, self.matcher_id),
                encode_status(self.matcher_id, state, role="matcher",  # type: ignore[arg-type]
                              timestamp=self._wall_clock(),
                              session_present=self._session_present if state == "online"
                              else None),
                qos=1, retain=True,
            )
        except Exception as error:  # the status is for viewers and cameras; never fatal
            logger.warning("plane %d: could not publish the matcher status: %s",
                           self.plane_id, error)

    def _on_connected(self, session_present: bool) -> None:
        """Transport hook, on its thread: after a reconnection, acknowledge nothing until
        the lease is confirmed again."""
        self._connections += 1
        self._session_present = session_present
        if self._connections > 1 and self._started:
            logger.warning("plane %d: reconnected (session present: %s); checking the lease "
                           "before acknowledging again", self.plane_id, session_present)
            if self._lease is not None:
                self._receiving.clear()
                self._lease.recheck()
            else:
                self._announce("online")

    def _lease_confirmed(self) -> None:
        self._receiving.set()
        self._announce("online")

    def _lease_lost(self, reason: str) -> None:
        self._receiving.clear()
        self._fail(LeaseLost(f"plane {self.plane_id}: lease lost ({reason})"), "lease")

    def _recover(self) -> None:
        released = self.store.released_timestamp()
        self._orderer.restore(released, {
            camera: summary["max_timestamp"]
            for camera, summary in self.store.inbox_summary().items()
        })
        now = self.clock()
        pending = self.store.pending_entries()
        for entry in pending:
            self._orderer.add(entry, now)
        if self.retrack is not None and self.store.status_counts().get(LATE):
            self._late_at = now  # re-tracking looks at those it has not seen yet
        if released is not None or pending:
            logger.info(
                "plane %d: resumed at %s with %d pending messages",
                self.plane_id, released, len(pending),
            )

    def _fail(self, error: BaseException, role: str) -> None:
        """Record the first failure and stop the service (``stop`` raises it)."""
        # A cause the operator can fix (a deleted database, a lost lease) is one sentence;
        # anything else is a bug and keeps its traceback.
        expected = isinstance(error, CblrsError | LeaseLost) or (
            isinstance(error, TrackerProcessError) and "Traceback" not in str(error))
        logger.error("matcher service %s failed: %s", role, error,
                     exc_info=None if expected else error)
        if self._failure is None:
            self._failure = error
        self._stop.set()
        self._arrived.set()
        self._wake.set()

    # -- transport callbacks (transport thread) -----------------------------------------

    def _on_detections(self, delivery: Any) -> None:
        self._inbox.append(("detections", delivery, self._wall_clock()))
        self._arrived.set()

    def _on_status(self, delivery: Any) -> None:
        self._inbox.append(("status", delivery, self._wall_clock()))
        self._arrived.set()

    # -- receiver thread -----------------------------------------------------------------

    def _work(self) -> None:
        """Receiver thread: store and acknowledge deliveries, buffer them for the tracker."""
        try:
            while not self._stop.is_set():
                if not self._receiving.is_set():  # no verified lease: acknowledge nothing
                    self._receiving.wait(0.2)
                    continue
                self._arrived.wait(0.2)
                self._arrived.clear()  # before emptying the inbox, so no arrival is missed
                while self._receiving.is_set() and self._handle():
                    self._wake.set()
                    self._send_confirmations()
                    if self._stop.is_set():
                        break
                self._send_confirmations()
            # Stopping: with a flush, also store what is queued. Anything left is
            # unacknowledged, so the broker delivers it again later.
            while (self._flush_requested.is_set() and self._failure is None
                   and self._receiving.is_set() and self._handle()):
                pass
        except BaseException as error:  # surfaced by stop()
            self._fail(error, "receiver")
        finally:
            self._received_all.set()
            self._wake.set()

    def _handle(self) -> bool:
        """Store, acknowledge and buffer the next batch of deliveries; False if none."""
        # Taking the batch, late marking, storing and buffering happen as one step against
        # the release of groups (see the module docstring) and ``drained``.
        with self._state_lock:
            count = min(len(self._inbox), self.batch_size)
            if not count:
                return False
            self._handle_locked([self._inbox.popleft() for _ in range(count)])
            return True

    def _handle_locked(self, batch: list[tuple[str, Any, float]]) -> None:
        started = time.perf_counter()
        now = self.clock()
        counters: Counter[str] = Counter()
        accepted: list[tuple[InboxEntry, str, float]] = []
        acknowledge = []
        rejected: list[tuple[str, int, str]] = []
        for kind, delivery, received_at in batch:
            acknowledge.append(delivery)
            if kind == "status":
                self._status(delivery, now)
                continue
            if not delivery.payload:
                # An empty retained publish removes a retained message (a camera clearing its
                # detections topic); it is never a message.
                continue
            if delivery.retain and delivery.topic not in self._retained_warned:
                self._retained_warned.add(delivery.topic)
                logger.warning(
                    "plane %d: a retained message sits on %s (some client published with "
                    "retain); every new subscription receives it again. It is stored once "
                    "(duplicates are ignored); `cblrs camera` removes it when it starts.",
                    self.plane_id, delivery.topic)
            self._last_delivery = now
            counters["received"] += 1
            try:
                plane_id, camera = _parse_topic(delivery.topic)
                wire = self.policy.decode_wire(
                    delivery.payload, topic_camera=camera, now=received_at, topic_plane=plane_id
                )
            except TopicError:
                counters["rejected.bad_topic"] += 1
                self._rejections.log(logging.WARNING, "bad_topic",
                                     "plane %d: rejected a message on %s: not a detections "
                                     "topic", self.plane_id, delivery.topic)
                continue
            except RejectedMessage as error:
                reason = error.reason.value
                counters[f"rejected.{reason}"] += 1
                self._rejections.log(logging.WARNING, reason,
                                     "plane %d: rejected a message on %s (%s): %s",
                                     self.plane_id, delivery.topic, reason, error)
                sequence = peek_sequence(delivery.payload, camera)
                if sequence is not None:
                    rejected.append((camera, sequence, reason))
                continue
            late = self._orderer.is_late(wire.timestamp)
            accepted.append((InboxEntry.from_wire(wire), LATE if late else PENDING, received_at))
        inserted = self.store.insert_messages(accepted, counters)
        if counters.get("conflicts"):
            self._rejections.log(
                logging.ERROR, "conflicts",
                "plane %d: %d messages repeat a stored camera and sequence number with other "
                "content (another run of a camera reusing its numbers: give it another "
                "--first-sequence); the stored ones are kept, these are counted as conflicts",
                self.plane_id, counters["conflicts"])
        # Acknowledge only now: everything above is durably stored (or rejected on purpose).
        for delivery in acknowledge:
            delivery.ack()
        for entry, _, _ in accepted:  # new or duplicates: stored either way
            self._confirmations.add_stored(entry.camera_id, entry.sequence)
        for camera, sequence, reason in rejected:
            self._confirmations.add_rejected(camera, sequence, reason)
        self.reporter.stored(batch, accepted, inserted, counters, time.perf_counter() - started)
        stored = []
        for (entry, status, _), new in zip(accepted, inserted, strict=True):
            if not new:
                continue
            stored.append(entry)
            self._active_this_run.add(entry.camera_id)
            if status == PENDING:
                self._orderer.add(entry, now)
            else:
                self._orderer.heard(entry.camera_id, now)
                if self.retrack is not None:
                    self._late_at = now
        if self.observer is not None and hasattr(self.observer, "on_stored") and stored:
            self.observer.on_stored(stored, self._wall_clock())

    def _retain(self) -> None:
        """Retention thread: apply the retention policy every ``interval_s``."""
        policy = self.retention
        if policy is None or not policy.enabled:
            return
        try:
            while not self._stop.wait(policy.interval_s):
                apply_retention(self.store, policy, self._wall_clock())
        except BaseException as error:  # surfaced by stop(): a store that fails, fails
            self._fail(error, "retention")

    def _send_confirmations(self, force: bool = False) -> None:
        """Publish the buffered confirmations, at most every ``confirm_interval_s``."""
        now = time.monotonic()
        if not force and now - self._last_confirmation < self.confirm_interval_s:
            return
        if not self._confirmations:
            return
        self._last_confirmation = now
        for topic, payload in self._confirmations.take():
            try:
                self.transport.publish(topic, payload, qos=1)
            except Exception as error:  # a camera sends again what it does not hear about
                logger.warning("plane %d: could not publish confirmations on %s: %s",
                               self.plane_id, topic, error)

    def _status(self, delivery: Any, now: float) -> None:
        try:
            plane_id, camera = parse_status_topic(delivery.topic)
            status = decode_status(delivery.payload)
        except (TopicError, RejectedMessage) as error:
            logger.debug("ignored status on %s: %s", delivery.topic, error)
            return
        if camera not in self._offline or plane_id != self.plane_id:
            return
        self.reporter.status(camera, status.state == "online")
        if status.state == "online":
            self._offline[camera] = self._final_offline[camera] = False
            self._offline_at[camera] = None
            self._active_this_run.add(camera)
            self._orderer.set_offline(camera, False)
            self._orderer.heard(camera, now)
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
                self._orderer.set_offline(camera, True)
        logger.info("plane %d: camera %s is %s", self.plane_id, camera, status.state)

    # -- releaser and collector threads ---------------------------------------------------

    def _release(self) -> None:
        """Releaser thread: send ready groups to the tracker process, then let it stop."""
        assert self._tracker is not None
        try:
            while not self._received_all.is_set():
                self._wake.wait(0.05 if len(self._orderer) else 0.2)
                self._wake.clear()
                self._release_ready()
                self._retrack_if_due()
            if self._failure is None and self._flush_requested.is_set():
                self._release_ready()
                self._release_ready(force=True)
                self._retrack_if_due(force=True)
        except TrackerProcessError as error:
            if not self._abandoning():  # else: the tracker process left as it was told
                self._fail(error, "releaser")
        except BaseException as error:  # surfaced by stop()
            self._fail(error, "releaser")
        finally:
            # A flushed stop ends the stream: the analytics end every track, as offline.
            self._tracker.finish(flush=self._flush_requested.is_set() and self._failure is None)

    def _abandoning(self) -> bool:
        """Stopping without a flush: nothing more is released (it stays pending)."""
        return self._stop.is_set() and not self._flush_requested.is_set()

    def _release_ready(self, force: bool = False) -> None:
        assert self._tracker is not None
        while self._failure is None and not self._abandoning():
            with self._state_lock:
                batch: Batch = self._orderer.release(
                    self.clock(), force=force, limit=self.groups_per_commit
                )
                if not batch:
                    return
                # From now on a message at or before these timestamps is late; the store
                # records the same timestamp when the windows are committed.
                self._inflight.append(batch)
            if self.observer is not None and hasattr(self.observer, "on_released"):
                self.observer.on_released([timestamp for timestamp, _ in batch],
                                          self._wall_clock())
            self._tracker.submit(batch)  # blocks while the tracker process is behind

    def _retrack_if_due(self, force: bool = False) -> None:
        """Ask the tracker process to track the late messages once none has come for
        ``retrack.delay_s`` (``force``: now), after the groups already sent."""
        assert self._tracker is not None
        with self._state_lock:
            if self._late_at is None or self.retrack is None or self._failure is not None \
                    or self._abandoning():
                return
            if not force and self.clock() - self._late_at < self.retrack.delay_s:
                return
            self._late_at = None
            self._retracks_inflight += 1
        self._tracker.submit("retrack")

    def _collect(self) -> None:
        """Collector thread: publish what the tracker process committed, tell the observer."""
        assert self._tracker is not None
        try:
            while True:
                try:
                    answer = self._tracker.receive()
                except EOFError:
                    if self._abandoning():
                        return  # it left without answering for what it abandoned
                    self._tracker.process.join(1.0)  # for its exit code
                    # A tracker process that found its database gone exits in one line; the
                    # operator's sentence is the database's (StoreError), not the exit code.
                    self.store.check_file()
                    raise TrackerProcessError(
                        f"the tracker process exited (code {self._tracker.process.exitcode})"
                        " without answering"
                    ) from None
                if answer[0] == "stopped":
                    return
                if answer[0] == "failed":
                    separator = "\n" if "Traceback" in answer[1] else " "
                    raise TrackerProcessError(f"the tracker process failed:{separator}{answer[1]}")
                if answer[0] == "retracked":  # late messages tracked: corrected updates
                    _, results, counters, report = answer
                    self.reporter.tracked([], report)
                    if self.reporter.metrics is not None:
                        self.reporter.metrics.retracked(counters)
                    for timestamp, tracks, payload in results:
                        self._publish(timestamp, [], tracks, payload, corrected=True)
                    if counters.get("late_tracked") or counters.get("late_untracked"):
                        logger.info("plane %d: re-tracked %d messages: %d late ones tracked, "
                                    "%d too old to track", self.plane_id,
                                    counters.get("retracked", 0), counters.get("late_tracked", 0),
                                    counters.get("late_untracked", 0))
                    with self._state_lock:
                        self._retracks_inflight -= 1
                    continue
                if answer[0] == "flushed":  # the end of the stream: what the matcher held
                    _, timestamp, tracks, payload, report = answer
                    if len(tracks):
                        self._publish(timestamp, [], tracks, payload)
                    self.reporter.tracked([(timestamp, len(tracks))] if len(tracks) else [],
                                          report)
                    continue
                _, results, _, report = answer
                batch = self._inflight[0]
                self.reporter.tracked([(item[0], len(item[1])) for item in results], report)
                for (timestamp, tracks, payload), (_, entries) in zip(results, batch, strict=True):
                    started = time.perf_counter()
                    self._publish(timestamp, entries, tracks, payload)
                    if self.reporter.metrics is not None:
                        self.reporter.metrics.published(time.perf_counter() - started)
                with self._state_lock:
                    self._inflight.popleft()
        except BaseException as error:  # surfaced by stop()
            self._fail(error, "tracker")

    def _publish(
        self, timestamp: float, entries: list[InboxEntry], tracks: Tracks, payload: bytes | None,
        corrected: bool = False,
    ) -> None:
        if payload is not None:
            try:
                self.transport.publish(tracks_topic(self.plane_id), payload, qos=1)
            except Exception:  # a viewer feed must never stop the matcher
                logger.exception("could not publish tracks of %s", timestamp)
        if not corrected and self.observer is not None and hasattr(self.observer, "on_group"):
            self.observer.on_group(timestamp, entries, tracks, self._wall_clock())

    # -- queries (any thread) --------------------------------------------------------------

    def idle_seconds(self) -> float:
        """Seconds (service clock) since the last detections delivery."""
        return self.clock() - self._last_delivery

    def buffered(self) -> int:
        """Messages waiting in the ordering buffer."""
        with self._state_lock:
            return len(self._orderer)

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

    def lag(self, now: float) -> float:
        """Seconds from the capture of the oldest message waiting for tracking (buffered or
        with the tracker process) to ``now`` (seconds since 1970); 0 when none waits."""
        with self._state_lock:
            oldest = [self._orderer.oldest()]
            if self._inflight:
                oldest.append(self._inflight[0][0][0])
        times = [value for value in oldest if value is not None]
        return max(0.0, now - min(times)) if times else 0.0

    def drained(self) -> bool:
        """Nothing waiting: no delivery to store, no buffered group, no group being tracked,
        no late message waiting to be re-tracked."""
        with self._state_lock:
            return (not self._inbox and not len(self._orderer) and not self._inflight
                    and self._late_at is None and not self._retracks_inflight)

    def failed(self) -> bool:
        """The error that stopped the service, or None."""
        return self._failure is not None

    def health(self) -> tuple[bool, str]:
        """``/healthz``: the service runs (no thread nor the tracker process has failed)."""
        if self._failure is not None:
            return False, f"failed: {self._failure}"
        if self._tracker is not None and not self._tracker.process.is_alive() \
                and not self._stop.is_set():
            return False, "the tracker process has gone"
        return True, ""

    def ready(self) -> tuple[bool, str]:
        """``/readyz``: started, healthy and connected to the broker."""
        healthy, reason = self.health()
        if not healthy:
            return False, reason
        if not self._started:
            return False, "starting"
        if not getattr(self.transport, "connected", True):
            return False, "not connected to the broker"
        return True, ""

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
            "buffered_groups": self._orderer.groups,
            "inbox": summary["inbox"],
            "track_ids": summary["track_ids"],
            "released_timestamp": self._orderer.released,
            "offline_cameras": sorted(c for c, off in self._offline.items() if off),
            "session_takeovers": int(getattr(self.transport, "takeovers", 0)),
            "clocks": clock_report(self.store.matcher_state(), self.camera_ids),
        }


@functools.cache
def _process_context() -> Any:
    """The ``multiprocessing`` context of tracker processes: a fork server.

    Forking from a server that has already imported the tracker (and not from this process,
    whose threads may hold locks) starts each tracker process quickly and safely.
    """
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["cblrs.runtime.matcher.tracker_process", "cblrs.matching"])
    return context


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
