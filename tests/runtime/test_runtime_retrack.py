"""Re-tracking late messages from snapshots (issue 20 item 1), at the store's level: which
snapshot is used, what is replaced, what stays untracked. The services and real processes
are tested in ``test_runtime_fault_tracks_late.py`` and
``test_runtime_fault_tracks_late_mqtt.py`` (item 1) and ``test_runtime_services.py``."""

from __future__ import annotations

import numpy as np
import pytest

from cblrs.detections import CameraMessage
from cblrs.errors import CblrsError
from cblrs.matching import make_matcher
from cblrs.plane import PlaneSet, PlaneSpec
from cblrs.runtime.matcher.retention import RetentionPolicy, apply_retention
from cblrs.runtime.matcher.retrack import RetrackPolicy, Snapshots, retrack
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.matcher.store_rows import InboxEntry
from cblrs.runtime.matcher.store_schema import LATE, PENDING, PROCESSED

CAMERAS = ["A", "B"]
NOW = 1_800_000_000.0


def _matcher():
    return make_matcher("fusion", PlaneSet([PlaneSpec(1, (0.0, 0.0), 20.0, 20.0)]), CAMERAS)


def _entry(camera: str, sequence: int) -> InboxEntry:
    """One person walking along x, seen by both cameras, 10 frames a second."""
    message = CameraMessage(
        camera, sequence, NOW + 0.1 * sequence, sequence, np.array([[0.0, 0, 10, 10]]),
        np.array([0.9]), np.array([0]), np.array([[1000 + 100 * sequence, 2000, 1]]))
    return InboxEntry.from_message(message)


def _track(store: RuntimeStore, matcher, snapshots: Snapshots, groups, late=()) -> None:
    """Store and track ``groups`` (sequence numbers, both cameras each), as the service and
    its tracker process do; ``late``: B's sequences withheld, stored late afterwards."""
    for sequence in groups:
        entries = [_entry(camera, sequence) for camera in CAMERAS
                   if not (camera == "B" and sequence in late)]
        store.insert_messages([(entry, PENDING, NOW) for entry in entries])
        timestamp = entries[-1].timestamp
        tracks = matcher.update(timestamp, [entry.message() for entry in entries])
        state = matcher.get_state()
        keys = [(entry.camera_id, entry.sequence) for entry in entries]

        def also(cursor, timestamp=timestamp, state=state, keys=keys):
            if snapshots.due(timestamp):
                snapshots.taking(timestamp)
                snapshots.write(cursor, timestamp, state, keys)

        store.commit_group(keys, tracks, state, timestamp, {"processed": len(keys)}, also=also)
    store.insert_messages([(_entry("B", sequence), LATE, NOW) for sequence in late])


def _undisturbed(tmp_path, groups) -> np.ndarray:
    with RuntimeStore(tmp_path / "undisturbed.db") as store:
        matcher = _matcher()
        snapshots = Snapshots(store, RetrackPolicy(snapshot_interval_s=0.5))
        _track(store, matcher, snapshots, groups)
        return store.tracks()


def test_late_messages_are_retracked_from_the_snapshot_before_them(tmp_path):
    groups, late = range(40), (22, 23)
    expected = _undisturbed(tmp_path, groups)
    with RuntimeStore(tmp_path / "late.db") as store:
        matcher = _matcher()
        snapshots = Snapshots(store, RetrackPolicy(snapshot_interval_s=0.5))
        snapshots.start(matcher.get_state())
        _track(store, matcher, snapshots, groups, late)
        done = retrack(store, matcher, CAMERAS, snapshots)
        assert done.corrected_from == pytest.approx(NOW + 2.0)  # snapshots every 0.5 s
        assert done.counters["late_tracked"] == 2 and done.counters["retracked"] == 2 * 19
        assert store.status_counts() == {PROCESSED: 80}
        actual = store.tracks()
        np.testing.assert_array_equal(actual.track_id, expected.track_id)
        np.testing.assert_array_equal(actual.world_xy, expected.world_xy)
        # Nothing new: a second call re-tracks nothing.
        assert retrack(store, matcher, CAMERAS, snapshots).counters == {}


def test_a_late_message_before_every_snapshot_stays_late_and_is_counted(tmp_path):
    with RuntimeStore(tmp_path / "m.db") as store:
        matcher = _matcher()
        snapshots = Snapshots(store, RetrackPolicy(snapshot_interval_s=0.5, max_snapshots=2))
        _track(store, matcher, snapshots, range(20), late=(3,))
        rows = len(store.tracks())
        done = retrack(store, matcher, CAMERAS, snapshots)
        assert done.counters == {"late_untracked": 1} and not done.windows
        assert store.status_counts() == {PROCESSED: 39, LATE: 1}
        assert len(store.tracks()) == rows
        assert retrack(store, matcher, CAMERAS, snapshots).counters == {}  # counted once


def test_no_snapshot_before_rows_retention_deleted(tmp_path):
    """Re-tracking from a snapshot older than deleted inbox rows would lose them: such
    snapshots are dropped, the one after them is used."""
    with RuntimeStore(tmp_path / "m.db") as store:
        matcher = _matcher()
        snapshots = Snapshots(store, RetrackPolicy(snapshot_interval_s=0.5))
        snapshots.start(matcher.get_state())
        _track(store, matcher, snapshots, range(20), late=(17,))
        # The inbox rows up to 1.2 s are deleted (by age, for the test).
        deleted = apply_retention(store, RetentionPolicy(max_age_s=1.25, max_bytes=None),
                                  NOW + 2.5)
        assert deleted["inbox"] == 2 * 13
        assert store.get_meta("deleted_until.inbox") == pytest.approx(NOW + 1.2)
        done = retrack(store, matcher, CAMERAS, snapshots)
        assert done.corrected_from == pytest.approx(NOW + 1.5)
        assert done.counters["late_tracked"] == 1


@pytest.mark.parametrize("options, message", [
    ({"snapshot_interval_s": -1.0}, "snapshot_interval_s must be a finite number >= 0"),
    ({"delay_s": float("nan")}, "delay_s must be a finite number >= 0"),
    ({"max_snapshots": 0}, "keeps at least one snapshot"),
])
def test_bad_policies_are_refused_in_one_sentence(options, message):
    with pytest.raises(CblrsError, match=message):
        RetrackPolicy(**options)
