"""The releaser and collector of a :class:`~cblrs.runtime.matcher.matcher_service.MatcherService`
(:class:`_Releaser`): step 4 of the service, on two threads.

The releaser sends the ordering's released groups (and re-tracking of late messages, when
due) to the tracker process; the collector takes its answers, the groups' tracks committed
in the store, and publishes them on ``cblrs/<plane>/tracks`` (and corrected rows after
re-tracking).
"""

from __future__ import annotations

import logging
import time

from cblrs.detections import Tracks
from cblrs.runtime.matcher.matcher_state import _MatcherState
from cblrs.runtime.matcher.store_rows import InboxEntry
from cblrs.runtime.matcher.tracker_process import Batch, TrackerProcessError
from cblrs.runtime.transport.topics import tracks_topic

logger = logging.getLogger("cblrs.runtime.matcher.matcher_service")
"""The service's logger: its parts log under the one name."""


class _Releaser(_MatcherState):
    """The releaser and collector threads of a matcher service."""

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
