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

:class:`MatcherService` keeps the lifecycle and the queries; its state and failure handling are
in :mod:`~cblrs.runtime.matcher.matcher_state`, steps 1-3 (the receiver thread) in
:mod:`~cblrs.runtime.matcher.matcher_receiver`, step 4 (the releaser and collector threads) in
:mod:`~cblrs.runtime.matcher.matcher_releaser`; the steps' own logic lives in their modules
(wire, store, ordering, the matchers, online analytics).
"""

from __future__ import annotations

import functools
import logging
import multiprocessing
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

from cblrs.detections import Tracks
from cblrs.matching.fusion import clock_report
from cblrs.runtime.matcher.lease import PlaneLease
from cblrs.runtime.matcher.matcher_receiver import _Receiver
from cblrs.runtime.matcher.matcher_releaser import _Releaser
from cblrs.runtime.matcher.matcher_state import LeaseLost
from cblrs.runtime.matcher.store import LATE, RuntimeStore
from cblrs.runtime.matcher.tracker_process import TrackerProcess
from cblrs.runtime.transport.topics import (
    detections_filter,
    matcher_status_topic,
    status_filter,
)
from cblrs.runtime.wire import encode_status

logger = logging.getLogger(__name__)

COUNTER_NAMES = ("received", "accepted", "duplicates", "conflicts", "late", "processed",
                 "groups", "tracks", "retracks", "retracked", "late_tracked", "late_untracked")
"""Counters every summary shows (rejections add ``rejected.<reason>``)."""


class MatcherService(_Receiver, _Releaser):
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
            (:class:`~cblrs.runtime.matcher.store_rows.InboxEntry`) are stored and acknowledged,
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

    # -- lifecycle -------------------------------------------------------------------------

    def start(self, connect: bool = True,
              on_started: Callable[[], None] | None = None) -> None:
        """Resume from the store, start the tracker process and the threads, subscribe.

        Args:
            connect: also connect the transport (else the caller connects it afterwards).
            on_started: called once everything runs, just before the "online" status goes
                out (``cblrs matcher`` arms its clean stop there: whoever saw "online" and
                sends SIGTERM gets a clean stop and its summary, not an aborted start-up).
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
        if on_started is not None:
            on_started()
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

    # -- queries (any thread) --------------------------------------------------------------

    def idle_seconds(self) -> float:
        """Seconds (service clock) since the last detections delivery."""
        return self.clock() - self._last_delivery

    def buffered(self) -> int:
        """Messages waiting in the ordering buffer."""
        with self._state_lock:
            return len(self._orderer)

    def cameras_done(self, after: float | None = None) -> bool:
        """Whether every camera has ended its stream with its own "offline" status.

        A camera counts when it went offline after being online or sending during this
        run, or when its "offline" is newer than everything the store holds from it (a
        replay that finished while this service was down). A last will (a dropped
        connection) does not count. With ``after`` (seconds since 1970), an "offline"
        published before it does not count either: an earlier run's end, when the caller
        starts the cameras again (``cblrs up --until-done`` on a finished run's folder).
        """
        summary = None
        for camera in self.camera_ids:
            if not self._final_offline[camera]:
                return False
            offline_at = self._offline_at[camera]
            if after is not None and (offline_at is None or offline_at < after):
                return False
            if camera in self._active_this_run:
                continue
            if summary is None:
                summary = self.store.inbox_summary()
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


def stored_tracks(store: RuntimeStore) -> Tracks:
    """All track rows of a store (convenience for callers holding only the service)."""
    return store.tracks()


def inbox_keys(store: RuntimeStore) -> dict[str, set[int]]:
    """``camera -> {sequence}`` of every message in a store's inbox."""
    keys: dict[str, set[int]] = defaultdict(set)
    for stored in store.messages():
        keys[stored.message.camera_id].add(stored.message.sequence)
    return dict(keys)
