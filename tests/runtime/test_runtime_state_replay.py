"""The tracker process saves its matcher's state now and then, not with every group.

Groups committed after the last saved state are kept in the store's ``replay`` table; a
resumed tracker process restores the state and updates the matcher with them again. Here the
tracker process's main function runs in this process on two real WILDTRACK cameras: first a
part of the windows with the state saved only once (so most groups are to be replayed), then
a resumed run on the same database with the rest. The stored tracks must be the in-process
pipeline's, row for row.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cblrs.datasets import load_scene
from cblrs.matching import make_matcher
from cblrs.pipeline import camera_messages, render_scene_references, scene_planes, track_scene
from cblrs.runtime.matcher import tracker_process
from cblrs.runtime.matcher.ordering import Orderer
from cblrs.runtime.matcher.retrack import RetrackPolicy
from cblrs.runtime.matcher.store import PENDING, InboxEntry, RuntimeStore

CAMERAS = ("CVLab1", "CVLab2")
EPOCH = 1_700_000_000.0
PLANE = 1


@pytest.fixture(scope="module")
def case(wildtrack_root):
    scene = load_scene(wildtrack_root).select_frames(0, 195)
    keep = [scene.camera_names.index(name) for name in CAMERAS]
    scene = replace(scene, cameras=[scene.cameras[index] for index in keep],
                    detections=[[row[index] for index in keep] for row in scene.detections],
                    timestamps=EPOCH + scene.timestamps)
    references = render_scene_references(scene)
    expected = track_scene(scene, matcher=make_matcher("fusion", scene_planes(scene),
                                                       list(CAMERAS)),
                           references=references).tracks
    entries = [InboxEntry.from_message(message)
               for message in camera_messages(scene, references)]
    return scene, references, entries, expected


class Requests:
    """The service's end of the requests pipe: these batches, then ``last``; ``busy``: the
    next batch is always already waiting (so no state is saved between batches)."""

    def __init__(self, batches, last, busy):
        self.items = [*batches, last]
        self.busy = busy

    def recv(self):
        return self.items.pop(0)

    def poll(self):
        return self.busy


class Results:
    def __init__(self):
        self.answers = []

    def send(self, answer):
        assert answer[0] != "failed", answer[1]
        self.answers.append(answer)


def run(store, scene, references, batches, last, busy=True, snapshots=None):
    """The tracker process's main function, in this process, on ``store``'s file."""
    results = Results()
    matcher = make_matcher("fusion", scene_planes(scene), list(CAMERAS))
    matcher.set_views(references)  # as `cblrs matcher` does from its references
    tracker_process.run(
        Requests(batches, last, busy), results, matcher, store.share(),
        store.claim(), PLANE, list(CAMERAS), True, None, None, snapshots or RetrackPolicy())
    return results.answers


def test_a_resumed_tracker_replays_the_groups_after_its_saved_state(case, tmp_path):
    scene, references, entries, expected = case
    orderer = Orderer(list(CAMERAS))
    for entry in entries:
        orderer.add(entry, 0.0)
    windows = orderer.release(0.0, force=True)
    batches = [windows[start:start + 3] for start in range(0, len(windows), 3)]
    half = len(batches) // 2
    with RuntimeStore(tmp_path / "matcher.db") as store:
        store.insert_messages([(entry, PENDING, EPOCH) for entry in entries])
        # No snapshot is due (a snapshot saves the state too).
        answers = run(store, scene, references, batches[:half], None,
                      snapshots=RetrackPolicy(snapshot_interval_s=1e6))
        assert [answer[0] for answer in answers] == ["tracked"] * half + ["stopped"]
        # The state was saved with the first batch only: the others wait to be replayed.
        replayed = store.replay_groups()
        assert len(replayed) == sum(len(batch) for batch in batches[1:half]) > 10
        assert [timestamp for timestamp, _ in replayed] == \
            [timestamp for batch in batches[1:half] for timestamp, _ in batch]
        answers = run(store, scene, references, batches[half:], "flush", busy=False)
        assert answers[-1][0] == "stopped"
        assert len(store.replay_groups()) < len(replayed)  # saved while idle
        tracks = store.tracks()
    assert len(tracks) == len(expected) > 100
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)


def test_an_idle_tracker_saves_its_state_every_few_seconds_of_capture_time(case, tmp_path):
    scene, references, entries, _ = case
    orderer = Orderer(list(CAMERAS))
    for entry in entries:
        orderer.add(entry, 0.0)
    windows = orderer.release(0.0, force=True)
    with RuntimeStore(tmp_path / "matcher.db") as store:
        store.insert_messages([(entry, PENDING, EPOCH) for entry in entries])
        run(store, scene, references, [[window] for window in windows], None, busy=False)
        saved_from = store.released_timestamp() - tracker_process.STATE_INTERVAL_S
        left = store.replay_groups()
        # Never more than the groups of the last interval wait to be replayed.
        assert all(timestamp > saved_from for timestamp, _ in left)
        assert len(left) < len(windows) // 4
        assert store.matcher_state() is not None
