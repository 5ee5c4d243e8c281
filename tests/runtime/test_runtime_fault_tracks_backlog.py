"""Stopping a matcher with a tracking backlog (issue 20, item 5): prompt, clean, and the
restart on the same database ends with the tracks of an uninterrupted run (the service with
a deliberately slow tracker, in process).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
from waiting import wait_until

from cblrs.detections import CameraMessage
from cblrs.matching import make_matcher
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_schema import PENDING, PROCESSED
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.topics import detections_topic
from cblrs.runtime.wire import encode_message

# -- item 5 ----------------------------------------------------------------------------------


def _square_plane():
    return PlaneSet([PlaneSpec(1, (0.0, 0.0), 20.0, 20.0)])


def _message(camera: str, sequence: int, timestamp: float) -> bytes:
    """One person at a spot that moves with the sequence number."""
    message = CameraMessage(
        camera, sequence, timestamp, sequence, np.array([[0.0, 0, 10, 10]]), np.array([0.9]),
        np.array([0]), np.array([[1000 + 100 * sequence, 2000, 1]]),
    )
    return encode_message(message, 1)


class _SlowMatcher:
    """The fusion tracker taking ``seconds`` per group (module level: it pickles into the
    tracker process): a backlog of minutes."""

    def __init__(self, seconds: float):
        self.inner = make_matcher("fusion", _square_plane(), ["A", "B"])
        self.seconds = seconds

    def update(self, timestamp, messages):
        time.sleep(self.seconds)
        return self.inner.update(timestamp, messages)

    def flush(self):
        return self.inner.flush()

    def get_state(self):
        return self.inner.get_state()

    def set_state(self, state):
        self.inner.set_state(state)


def _publish_groups(broker, now: float, groups: int) -> None:
    sender = InProcessTransport(broker, "publisher", persistent=False)
    sender.connect()
    for sequence in range(groups):
        for camera in ("A", "B"):
            sender.publish(detections_topic(1, camera),
                           _message(camera, sequence, now + 0.1 * sequence))
    sender.close()


def _track_to_the_end(database, now: float, groups: int) -> RuntimeStore:
    """A service on ``database`` (resuming what it holds) fed every group, flushed."""
    broker = InProcessBroker()
    store = RuntimeStore(database)
    service = MatcherService(InProcessTransport(broker, "matcher"), store,
                             make_matcher("fusion", _square_plane(), ["A", "B"]), 1, ["A", "B"],
                             window_s=60)
    service.start()
    _publish_groups(broker, now, groups)  # what the store holds already counts as duplicates
    wait_until(lambda: store.counters().get("accepted", 0) == 2 * groups
               and service.drained(), 120, "every message stored and tracked")
    service.close(flush=True)
    return store


def test_item5_stopping_with_a_backlog_is_prompt_and_the_restart_tracks_it(tmp_path):
    """Issue 20 item 5: a stop without flush does not track the backlog (a minute here); it
    ends in seconds without a failure, the backlog stays pending, and a restart on the same
    database ends with the tracks of an uninterrupted run."""
    broker = InProcessBroker()
    now, groups = time.time(), 300
    store = RuntimeStore(tmp_path / "stopped.db")
    service = MatcherService(InProcessTransport(broker, "matcher"), store, _SlowMatcher(0.2),
                             1, ["A", "B"], window_s=60)
    service.start()
    _publish_groups(broker, now, groups)
    wait_until(lambda: store.counters().get("groups", 0) >= 5, 60, "tracking to begin")
    started = time.monotonic()
    service.close()  # raises if a thread or the tracker process failed
    stopped_in = time.monotonic() - started
    assert stopped_in < 15, f"the stop took {stopped_in:.1f} s (the backlog: {groups * 0.2} s)"
    assert service._tracker.process.exitcode == 0
    assert store.status_counts().get(PENDING, 0) > groups, "the backlog should stay pending"
    store.close()
    resumed = _track_to_the_end(tmp_path / "stopped.db", now, groups)
    undisturbed = _track_to_the_end(tmp_path / "undisturbed.db", now, groups)
    try:
        assert resumed.status_counts() == {PROCESSED: 2 * groups}
        expected, actual = undisturbed.tracks(), resumed.tracks()
        assert len(expected) >= groups
        np.testing.assert_array_equal(actual.track_id, expected.track_id)
        np.testing.assert_array_equal(actual.timestamp, expected.timestamp)
        np.testing.assert_array_equal(actual.world_xy, expected.world_xy)
    finally:
        resumed.close()
        undisturbed.close()


_LEFT_RUNNING = textwrap.dedent("""
    import sys, time
    sys.path[:0] = [{tests!r}, {here!r}]
    from waiting import wait_until
    from test_runtime_fault_tracks_backlog import _SlowMatcher, _publish_groups
    from cblrs.runtime.matcher.matcher_service import MatcherService
    from cblrs.runtime.matcher.store import RuntimeStore
    from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport

    broker, store = InProcessBroker(), RuntimeStore({database!r})
    service = MatcherService(InProcessTransport(broker, "matcher"), store, _SlowMatcher(0.2),
                             1, ["A", "B"], window_s=60)
    service.start()
    _publish_groups(broker, time.time(), 300)
    wait_until(lambda: store.counters().get("groups", 0) >= 5, 60, "tracking to begin")
    print("tracking", flush=True)
    raise SystemExit(3)  # an error on the way out: the service is never closed
""")


def test_a_program_that_exits_without_closing_its_service_does_not_hang(tmp_path):
    """The tracker process ignores SIGTERM (the service decides when it stops), which made
    multiprocessing's exit handler wait for it forever when a program left without closing
    its service; it now ends within seconds, with the program's own exit code, and what it
    had not committed stays pending for a restart."""
    here = Path(__file__).parent
    script = _LEFT_RUNNING.format(tests=str(here.parent), here=str(here),
                                  database=str(tmp_path / "left.db"))
    try:
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                              timeout=90)
    except subprocess.TimeoutExpired:
        raise AssertionError("the program hung at exit (its tracker process was left "
                             "running)") from None
    assert done.stdout.strip() == "tracking", done.stderr
    assert done.returncode == 3, done.stderr
    assert "was not stopped before the program's exit" in done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    with RuntimeStore(tmp_path / "left.db", read_only=True) as store:
        assert store.status_counts().get(PENDING, 0) > 0, "the backlog should stay pending"
