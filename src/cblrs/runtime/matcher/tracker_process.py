"""The matcher service's tracker process: track released groups, commit them, encode updates.

The matcher service (:mod:`cblrs.runtime.matcher.matcher_service`) receives, stores, acknowledges
and orders messages in its own process and sends each batch of released timestamp groups
here through a pipe. This process runs the matcher on them, commits the batch to the shared
SQLite store in one transaction (track rows, inbox rows marked processed, matcher state,
last released timestamp, counters; a thread copies the WAL into the database file, off the
writers' path) and answers with the tracks and the encoded track
updates, which the service publishes. Receiving and tracking thus run on two cores rather
than taking turns on one interpreter lock.

The process resumes the matcher from the state the store holds, so a service restarted on
the same database (after a crash of either process) continues from the last committed batch.
The state is not saved with every batch (with many cameras it is a few hundred kB of JSON,
longer to encode than a group is to track): a batch is committed with its groups' keys in the
store's ``replay`` table, and the state is saved on its own after a batch's answer, when no
batch is waiting and ``STATE_INTERVAL_S`` of capture time has passed (with a snapshot due,
too), or with a batch once ``MAX_REPLAY_GROUPS`` groups wait. A resumed process restores the
saved state and updates the matcher with the replayed groups again (their tracks are stored
already), which gives the state after the last committed group.

Messages (pickled) on the two pipes:

* service -> tracker: a batch ``[(timestamp, [InboxEntry, ...]), ...]`` (windows in time
  order, messages in time and camera order; entries travel as plain tuples), ``None``:
  commit nothing more and stop,
  ``"retrack"``: track the late messages stored since the last time
  (:mod:`cblrs.runtime.matcher.retrack`), answer ``("retracked", [(timestamp, tracks, payload or
  None), ...], counters, report)`` with the corrected updates, or
  ``"flush"``: the stream has ended: fuse and commit what the matcher still holds (its
  ``flush()``), count those rows and end every track of the analytics, answer
  ``("flushed", timestamp, tracks, payload or None, report)``, then stop;
* tracker -> service, in the order of the batches: ``("tracked", [(timestamp, tracks,
  payload or None), ...], counters, report)`` once a batch is committed (``report``: the
  stages' durations, the analytics events by kind, the zones' live occupancy and dwell);
  ``("failed", traceback)`` when tracking or committing raised (the process then exits);
  ``("stopped",)`` after ``None`` or ``"flush"``, or once the service abandoned what it sent
  (:meth:`TrackerProcess.abandon`, a stop without flush: the batch being tracked and those
  still in the pipe are not committed, and stay pending in the store).

With re-tracking on, the matcher's state is also kept as a snapshot after a group every
few seconds of capture time, in the transaction of its batch or, for a batch's last group,
with the state saved after its answer (:mod:`cblrs.runtime.matcher.retrack`).

With analytics, each group's rows are counted as soon as it is tracked
(:class:`~cblrs.runtime.outputs.online_analytics.OnlineAnalytics`, empty groups too), and the
events, counter increments and engine state go into the batch's transaction.
"""

from __future__ import annotations

import atexit
import gc
import logging
import math
import signal
import threading
import time
import traceback
import weakref
from collections.abc import Sequence
from typing import Any

# The fork server preloads this module: np.unique imports numpy.ma at its first call (numpy
# 2), 30-100 ms that would otherwise delay the first frame's tracks.
import numpy.ma  # noqa: F401

from cblrs.detections import Tracks
from cblrs.errors import CblrsError
from cblrs.runtime.matcher.retrack import RetrackPolicy, Snapshots, retrack, state_text
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_file import SharedStore, checkpoint_regularly
from cblrs.runtime.matcher.store_rows import InboxEntry
from cblrs.runtime.wire import encode_tracks

logger = logging.getLogger(__name__)

Batch = list[tuple[float, list[InboxEntry]]]
"""Released groups sent to the tracker process: ``(timestamp, entries in camera order)``."""

_entry = tuple.__new__  # an InboxEntry from its plain tuple, without a Python-level call


class TrackerProcessError(RuntimeError):
    """The tracker process failed (its traceback is the message) or exited unexpectedly."""


class TrackerProcess:
    """The tracker process of one matcher service, and the service's ends of its pipes.

    Args:
        context: the ``multiprocessing`` context that starts the process.
        matcher: the matcher (pickled into the process; it resumes from the store's state).
        shared: the service's store, shared for writing (:meth:`RuntimeStore.share`).
        tracker: the service's claim on the store (:meth:`RuntimeStore.claim`).
        plane_id: the plane served (track updates name it).
        camera_ids: the plane's cameras (track updates list them).
        publish_tracks: encode a track update per group.
        analytics: the plane's :class:`~cblrs.runtime.outputs.online_analytics.OnlineAnalytics`
            (pickled into the process; it resumes from the store), or None.
        retrack: snapshots and re-tracking of late messages (:mod:`cblrs.runtime.matcher.retrack`);
            None: neither (late messages stay untracked).
    """

    def __init__(
        self,
        context: Any,
        matcher: Any,
        shared: SharedStore,
        tracker: str,
        plane_id: int,
        camera_ids: Sequence[str],
        publish_tracks: bool,
        analytics: Any = None,
        retrack: RetrackPolicy | None = None,
    ):
        requests_reader, self._requests = context.Pipe(duplex=False)
        self._results, results_writer = context.Pipe(duplex=False)
        self._abandon = context.Event()
        self.process = context.Process(
            target=run,
            args=(requests_reader, results_writer, matcher, shared, tracker, plane_id,
                  list(camera_ids), publish_tracks, analytics, self._abandon, retrack),
            name=f"cblrs-tracker-{plane_id}",
            daemon=True,
        )
        self.process.start()
        # Only the child holds these ends now, so a child that dies closes the pipes:
        # ``receive`` then raises EOFError instead of waiting forever.
        requests_reader.close()
        results_writer.close()
        # A program that exits without closing its service (an error on its way out) would
        # otherwise hang: multiprocessing's exit handler terminates daemon children with
        # SIGTERM, which this process ignores, and then waits for them. Registered after
        # multiprocessing's own handler, this one runs first (atexit is last in, first out).
        self._at_exit = _stop_at_exit(weakref.ref(self))
        atexit.register(self._at_exit)

    def submit(self, batch: Batch) -> None:
        """Send a batch of released groups (blocks while the pipe is full).

        Raises:
            TrackerProcessError: the process has gone (its pipe is closed).
        """
        if isinstance(batch, list):
            # Plain tuples: a named tuple pickles through a Python call per entry, in the
            # service's GIL-bound threads; the tracker process makes them entries again.
            batch = [(timestamp, [tuple(entry) for entry in entries])
                     for timestamp, entries in batch]
        try:
            self._requests.send(batch)
        except (OSError, TypeError, ValueError) as error:
            # OSError: the process has gone; TypeError/ValueError: close() closed the pipe
            # under this send (a stop that did not wait for it).
            self.process.join(1.0)  # for its exit code
            raise TrackerProcessError(
                f"the tracker process exited (code {self.process.exitcode}) before taking "
                f"the next groups ({getattr(error, 'strerror', None) or error})"
            ) from None

    def finish(self, flush: bool = False) -> None:
        """Ask the process to stop after the batches already sent (a no-op once it has gone).

        Args:
            flush: first fuse and commit the messages the matcher still holds, and end every
                track of the analytics (the stream has ended).
        """
        try:
            self._requests.send("flush" if flush else None)
        except OSError:
            pass

    def abandon(self) -> None:
        """Stop without tracking what was sent and not yet committed (a stop without flush):
        the process commits nothing more and exits at its next group. Those messages stay
        pending in the store; a restarted service tracks them."""
        self._abandon.set()

    def receive(self) -> tuple:
        """The next answer of the process (blocks).

        Raises:
            EOFError: the process has gone.
        """
        return self._results.recv()

    def close(self, timeout: float) -> None:
        """Wait for the process to exit (terminate it after ``timeout``); close the pipes."""
        atexit.unregister(self._at_exit)
        self.process.join(timeout)
        if self.process.is_alive():
            logger.warning("tracker process %s did not stop within %.0f s; terminating it",
                           self.process.name, timeout)
            self.process.terminate()
            self.process.join(5)
        self._requests.close()
        self._results.close()


def _stop_at_exit(tracker: weakref.ref) -> Any:
    """An exit handler for a tracker process its program never closed: abandon what was
    sent (it stays pending in the store, as on a stop without flush), end the process's
    wait on the pipe, and kill it if it is still inside a group after a few seconds (its
    SQLite transaction then rolls back)."""

    def stop() -> None:
        process = tracker()
        if process is None or not process.process.is_alive():
            return
        logger.warning("tracker process %s was not stopped before the program's exit; "
                       "abandoning what it holds (it stays pending)", process.process.name)
        process.abandon()
        process._requests.close()  # the process's recv() ends: EOFError
        process.process.join(EXIT_GRACE_S)
        if process.process.is_alive():
            process.process.kill()
            process.process.join(5)

    return stop


def _next_request(requests: Any) -> Any:
    """The service's next request; ``None`` (stop) once the service has closed its end."""
    try:
        return requests.recv()
    except EOFError:
        return None


def run(
    requests: Any,
    results: Any,
    matcher: Any,
    shared: SharedStore,
    tracker: str,
    plane_id: int,
    camera_ids: list[str],
    publish_tracks: bool,
    analytics: Any = None,
    abandon: Any = None,
    retrack_policy: RetrackPolicy | None = None,
) -> None:
    """The tracker process's main function (see the module docstring for the protocol)."""
    # The service decides when this process stops: Ctrl-C in a terminal and systemd's SIGTERM
    # to the whole process group reach both; the service then finishes the batches it sent.
    # A service that dies closes the pipe, which ends this process too.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        store = RuntimeStore(shared.path, write_lock=shared.write_lock)
    except (CblrsError, OSError) as error:
        # The database vanished or changed before this process opened it (the receiver has
        # seen it too and stops the service, saying why): one line, no traceback.
        logger.warning("tracker process: %s", error)
        raise SystemExit(1) from None
    stop_checkpoints = threading.Event()
    checkpoints = threading.Thread(
        target=checkpoint_regularly, args=(shared.path, stop_checkpoints), daemon=True
    )
    checkpoints.start()
    try:
        state = store.matcher_state()
        if state is not None:
            matcher.set_state(state)
        # The groups committed after the saved state: their tracks are stored; updating the
        # matcher with them again gives its state after the last committed group.
        for timestamp, entries in store.replay_groups():
            matcher.update(timestamp, [entry.message() for entry in entries])
        if analytics is not None:
            analytics.resume(store)
        snapshots = None
        if retrack_policy is not None:
            snapshots = Snapshots(store, retrack_policy)
            if analytics is not None:
                analytics.log_increments = True  # a re-tracking takes back what was counted
            snapshots.start(matcher.get_state(),
                            None if analytics is None else analytics.get_state())
        # Everything alive now (modules, the matcher) lives as long as the process: keep it
        # out of the garbage collector's full passes, which would otherwise walk it all.
        gc.freeze()
        updates = 0
        released = store.released_timestamp()
        state = _StateSaving(released)
        abandoned = abandon.is_set if abandon is not None else lambda: False
        while not abandoned() and (batch := _next_request(requests)) is not None:
            if batch == "flush":
                if released is not None:
                    updates = _flush(store, matcher, analytics, released, tracker, results,
                                     publish_tracks, plane_id, updates, camera_ids)
                break
            if batch == "retrack":
                updates = _retrack(store, matcher, snapshots, tracker, results, publish_tracks,
                                   plane_id, updates, camera_ids, analytics)
                continue
            batch = [(timestamp, [_entry(InboxEntry, row) for row in rows])
                     for timestamp, rows in batch]
            tracked = []
            report = _Report(analytics)
            taken: list[tuple[int, float, Any, list[tuple[str, int]], Any]] = []
            snapshot_after = False  # a snapshot due after the batch's last group
            for timestamp, entries in batch:
                if abandoned():
                    break
                messages = [entry.message() for entry in entries]
                started = time.perf_counter()
                group_tracks = matcher.update(timestamp, messages)
                report.add("track", time.perf_counter() - started)
                tracked.append((timestamp, group_tracks))
                report.count(group_tracks, timestamp)
                if snapshots is not None and snapshots.due(timestamp):
                    if len(tracked) == len(batch):  # taken after the answer, off its path
                        snapshot_after = True
                        continue
                    snapshots.taking(timestamp)
                    # What the analytics counted so far is written before the snapshot,
                    # with their state then: a re-tracking from it takes back the rest.
                    taken.append((len(tracked) - 1, timestamp, state_text(matcher.get_state()),
                                  _keys_at(batch[:len(tracked)], timestamp), report.writes()))
            if abandoned():
                break  # a stop without flush: this batch stays pending in the store
            keys = [(entry.camera_id, entry.sequence) for _, entries in batch for entry in entries]
            tracks = Tracks.concatenate([group_tracks for _, group_tracks in tracked])
            counters = {"processed": len(keys), "groups": len(batch), "tracks": len(tracks)}
            counters.update(_clock_counters(matcher))
            released = batch[-1][0]
            # One snapshot after the last group: the file holds all of these groups or none,
            # with their analytics events, counts and state.
            started = time.perf_counter()
            also = counted = report.writes()
            if taken and snapshots is not None:
                rows = [len(group_tracks) for _, group_tracks in tracked]
                also = _snapshots_too(also, snapshots, taken, rows)
            # The matcher state is saved with the batch only when too many groups would have
            # to be replayed; otherwise the groups are (see _StateSaving).
            forced = state.forced(len(batch))
            store.commit_group(
                keys, tracks, matcher.get_state() if forced else None, released, counters,
                tracker=tracker, also=also,
                replay=None if forced else [
                    (timestamp, [(entry.camera_id, entry.sequence) for entry in entries])
                    for timestamp, entries in batch])
            state.committed(len(batch), released, saved=forced)
            report.add("commit", time.perf_counter() - started)
            answers = []
            for timestamp, group_tracks in tracked:
                updates += 1
                payload = None
                if publish_tracks:
                    payload = _encode(group_tracks, plane_id, updates, camera_ids, timestamp)
                answers.append((timestamp, group_tracks, payload))
            results.send(("tracked", answers, counters, report.summary()))
            if snapshot_after or state.due(released, busy=requests.poll()):
                # A snapshot here follows the batch's analytics writes: their state with it.
                _save_state(store, matcher, snapshots if snapshot_after else None, tracker,
                            released, _keys_at(batch, released),
                            None if counted is None else counted.state)
                state.committed(0, released, saved=True)
        results.send(("stopped",))
    except BaseException as error:
        # A cause the operator can fix is its one sentence; anything else, a traceback.
        text = str(error) if isinstance(error, CblrsError) else traceback.format_exc()
        try:
            results.send(("failed", text))
        except OSError:  # the service has gone too
            pass
        raise SystemExit(1) from None
    finally:
        stop_checkpoints.set()
        checkpoints.join()
        store.close()


EXIT_GRACE_S = 5.0
"""Seconds a tracker process left running at the program's exit has to end its group."""

STATE_INTERVAL_S = 2.0
"""Capture-time seconds between saves of the matcher state while groups keep coming."""

MAX_REPLAY_GROUPS = 300
"""Groups committed without the state, at most: a resumed matcher updates its saved state
with them again (:meth:`RuntimeStore.replay_groups`), which takes a fraction of a second."""


class _StateSaving:
    """When the tracker process saves its matcher's state.

    The state of a fusion tracker is a few hundred kB of JSON with many cameras: encoding it
    takes longer than tracking a group. So a batch is committed with its groups' keys
    (``replay``) instead, and the state is saved on its own, after the batch's answer (off
    the capture -> track path), once no batch is waiting and ``STATE_INTERVAL_S`` of capture
    time has passed; or with a batch when ``MAX_REPLAY_GROUPS`` would be exceeded.
    """

    def __init__(self, released: float | None):
        self.saved_at = -math.inf if released is None else released
        self.unsaved = MAX_REPLAY_GROUPS  # unknown after a restart: save soon

    def forced(self, groups: int) -> bool:
        return self.unsaved + groups > MAX_REPLAY_GROUPS

    def due(self, released: float, busy: bool) -> bool:
        return self.unsaved > 0 and not busy and released - self.saved_at >= STATE_INTERVAL_S

    def committed(self, groups: int, released: float, saved: bool) -> None:
        if saved:
            self.unsaved, self.saved_at = 0, released
        else:
            self.unsaved += groups


def _save_state(store: RuntimeStore, matcher: Any, snapshots: Snapshots | None, tracker: str,
                released: float, boundary: list[tuple[str, int]], analytics: Any = None) -> None:
    """Save the matcher state after the last committed batch (empties the replay table),
    with the snapshot due at its watermark if ``snapshots`` (``analytics``: the online
    analytics' state committed with that batch, or None), in one transaction."""
    text = state_text(matcher.get_state())
    also = None
    if snapshots is not None:
        snapshots.taking(released)

        def also(cursor: Any) -> None:
            snapshots.write(cursor, released, text, boundary, analytics=analytics)
    store.save_matcher_state(text, tracker=tracker, also=also)


def _keys_at(groups: Batch, timestamp: float) -> list[tuple[str, int]]:
    """Keys of the messages captured at ``timestamp`` among these groups'."""
    return [(entry.camera_id, entry.sequence) for _, entries in groups for entry in entries
            if entry.timestamp == timestamp]


def _snapshots_too(also: Any, snapshots: Snapshots,
                   taken: list[tuple[int, float, Any, list[tuple[str, int]], Any]],
                   rows: list[int]) -> Any:
    """The snapshots taken after some of the batch's groups (``(group index, watermark,
    state, keys at it, analytics writes until then)``; ``rows``: track rows per group), each
    after the analytics writes before it, then the batch's remaining extra writes."""
    def writes(cursor: Any) -> None:
        for index, released, state, boundary, counted in taken:
            if counted is not None:
                counted(cursor)
            snapshots.write(cursor, released, state, boundary, rows_after=sum(rows[index + 1:]),
                            analytics=None if counted is None else counted.state)
        if also is not None:
            also(cursor)
    return writes


def _retrack(store: RuntimeStore, matcher: Any, snapshots: Snapshots | None, tracker: str,
             results: Any, publish_tracks: bool, plane_id: int, updates: int,
             camera_ids: list[str], analytics: Any = None) -> int:
    """Track the late messages (:func:`cblrs.runtime.matcher.retrack.retrack`); one
    ``retracked`` answer with the corrected updates. Returns the update counter."""
    started = time.perf_counter()
    done = retrack(store, matcher, camera_ids, snapshots, tracker, analytics) \
        if snapshots is not None else None
    answers = []
    for timestamp, tracks in done.windows if done is not None else []:
        updates += 1
        payload = None
        if publish_tracks:
            payload = _encode(tracks, plane_id, updates, camera_ids, timestamp,
                              corrected_from=done.corrected_from)
        answers.append((timestamp, tracks, payload))
    counters = done.counters if done is not None else {}
    report = {"durations": {"retrack": [time.perf_counter() - started]},
              "events": done.events if done is not None else {},
              "live": None if analytics is None or done is None or not done.windows
              else analytics.live()}
    results.send(("retracked", answers, counters, report))
    return updates


def _clock_counters(matcher: Any) -> dict[str, int]:
    """Counters of the matcher's clock events (cameras found off, searched, back in line)."""
    events = getattr(matcher, "clock_events", None)
    if events is None:
        return {}
    counters: dict[str, int] = {}
    for event in events():
        name = f"clock_{event['kind']}"
        counters[name] = counters.get(name, 0) + 1
    return counters


class _Report:
    """What one batch did beyond tracking: its analytics (counted here, written in the
    batch's transaction) and how long its stages took (for the service's metrics)."""

    def __init__(self, analytics: Any):
        self.analytics = analytics
        self.durations: dict[str, list[float]] = {}
        self.events: dict[str, int] = {}

    def add(self, stage: str, seconds: float) -> None:
        self.durations.setdefault(stage, []).append(seconds)

    def count(self, tracks: Tracks, timestamp: float) -> None:
        if self.analytics is None:
            return
        started = time.perf_counter()
        for event in self.analytics.update(tracks, timestamp):
            self.events[event.kind] = self.events.get(event.kind, 0) + 1
        self.add("analytics", time.perf_counter() - started)

    def writes(self) -> Any:
        return None if self.analytics is None else self.analytics.take_writes()

    def summary(self) -> dict[str, Any]:
        return {
            "durations": self.durations,
            "events": self.events,
            "live": None if self.analytics is None else self.analytics.live(),
        }



def _flush(store: RuntimeStore, matcher: Any, analytics: Any, released: float, tracker: str,
           results: Any, publish_tracks: bool, plane_id: int, updates: int,
           camera_ids: list[str]) -> int:
    """The end of the stream: fuse what the matcher holds, count it, end every track of the
    analytics; one commit, one ``flushed`` answer. Returns the update counter."""
    flush = getattr(matcher, "flush", None)
    tracks = flush() if flush is not None else Tracks.empty()
    if not len(tracks) and analytics is None:
        # Nothing to commit, but the state is saved once more: the one saved last may be up to
        # STATE_INTERVAL_S of groups old (replayed on a restart), and what the service reports
        # at its end (its cameras' clocks) is read from it.
        store.save_matcher_state(state_text(matcher.get_state()), tracker=tracker)
        return updates
    report = _Report(analytics)
    report.count(tracks, released)
    if analytics is not None:
        for event in analytics.flush():
            report.events[event.kind] = report.events.get(event.kind, 0) + 1
    store.commit_group([], tracks, matcher.get_state(), released, {"tracks": len(tracks)},
                       tracker=tracker, also=report.writes())
    payload = None
    if publish_tracks and len(tracks):
        updates += 1
        payload = _encode(tracks, plane_id, updates, camera_ids, released)
    results.send(("flushed", released, tracks, payload, report.summary()))
    return updates


def _encode(
    tracks: Tracks, plane_id: int, sequence: int, camera_ids: list[str], timestamp: float,
    corrected_from: float | None = None,
) -> bytes | None:
    """The track update of one group; None (logged) if it cannot be encoded."""
    try:
        return encode_tracks(tracks, plane_id, sequence=sequence, cameras=camera_ids,
                             timestamp=timestamp, corrected_from=corrected_from)
    except Exception:  # a viewer feed must never stop the matcher
        logger.exception("could not encode the tracks of %s", timestamp)
        return None
