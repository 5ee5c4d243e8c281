"""Late messages are tracked (issue 20, item 1), in process: messages that arrive after their
window was released are re-tracked from a snapshot, the corrected tracks are published as
updates, and the online analytics follow the correction. The same with real processes on
Mosquitto is in test_runtime_fault_tracks_late_mqtt.py; the plant is in fault_tracks.py.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from fault_tracks import CAMERAS, EPOCH, TOTAL, assert_undisturbed, make_case
from waiting import wait_until

from cblrs.matching import make_matcher
from cblrs.pipeline import camera_messages, scene_planes
from cblrs.places import CountingLine, Places, Zone
from cblrs.runtime.matcher.matcher_service import MatcherService
from cblrs.runtime.matcher.retrack import RetrackPolicy
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.analytics_store import read_bins, read_counts, read_events, read_od
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics
from cblrs.runtime.transport.inprocess import InProcessBroker, InProcessTransport
from cblrs.runtime.transport.topics import detections_topic, tracks_topic
from cblrs.runtime.wire import TracksUpdate, decode_tracks, encode_message


@pytest.fixture(scope="module")
def case(wildtrack_root, tmp_path_factory) -> dict:
    return make_case(wildtrack_root, tmp_path_factory)


# -- item 1 ----------------------------------------------------------------------------------


def _places(tracks) -> Places:
    """A counting line across the middle of where the undisturbed tracks walk and a zone
    over half of it (from the data, so that people cross and visit)."""
    (x0, y0), (_, y1) = tracks.world_xy.min(axis=0), tracks.world_xy.max(axis=0)
    middle = float(np.median(tracks.world_xy[:, 0]))
    zone = np.array([[x0 - 1, y0 - 1], [middle, y0 - 1], [middle, y1 + 1], [x0 - 1, y1 + 1]])
    return Places(zones=(Zone("west", zone),),
                  lines=(CountingLine("middle", (middle, y0 - 1), (middle, y1 + 1)),))


def _analytics_of(database: Path) -> dict:
    """What the online analytics stored: counts, bins, OD and the events (by key)."""
    with RuntimeStore(database, read_only=True) as store:
        return {"counts": read_counts(store), "bins": read_bins(store), "od": read_od(store),
                "events": {event.body["key"]: event.body for event in read_events(store)}}


def _assert_same_analytics(actual: dict, expected: dict) -> None:
    """Equal; sums of seconds (dwell, occupancy) up to float rounding: a correction
    subtracts and adds them again."""
    assert actual["od"] == expected["od"]
    retracted = {body["retracted"] for body in actual["events"].values()
                 if body["kind"] == "event_retracted"}
    standing = {key for key, body in actual["events"].items()
                if body["kind"] != "event_retracted" and key not in retracted}
    assert sorted(standing) == sorted(expected["events"])
    for name in ("counts", "bins"):
        assert actual[name].keys() == expected[name].keys(), name
        for key, value in expected[name].items():
            assert actual[name][key] == pytest.approx(value, rel=1e-9, abs=1e-9), (name, key)


def _run_item1(case: dict, database: Path, late_sequences=(), updates=None) -> dict:
    """The matcher service (in-process broker) with re-tracking and analytics; CVLab2's
    ``late_sequences`` are sent only after their windows were released. Returns the
    store's counters after a flushed stop."""
    scene = case["scene"]
    messages = camera_messages(replace(scene, timestamps=EPOCH + scene.timestamps),
                               case["references"])
    late = [message for message in messages
            if message.camera_id == "CVLab2" and message.sequence in late_sequences]
    assert len(late) == len(late_sequences)
    broker = InProcessBroker()
    updates = [] if updates is None else updates
    viewer = InProcessTransport(broker, "viewer", persistent=False)
    viewer.subscribe(tracks_topic(1), lambda delivery: updates.append(
        decode_tracks(delivery.payload)))
    viewer.connect()
    store = RuntimeStore(database)
    tracker = make_matcher("fusion", scene_planes(scene), list(CAMERAS))
    tracker.set_views(case["references"])  # as track_scene and `cblrs matcher` do
    service = MatcherService(
        InProcessTransport(broker, "matcher"), store, tracker, 1, list(CAMERAS),
        window_s=10, retrack=RetrackPolicy(snapshot_interval_s=2.0, delay_s=0.3),
        analytics=OnlineAnalytics(_places(case["tracks"])))
    service.start()
    closed = False
    sender = InProcessTransport(broker, "cameras", persistent=False)
    sender.connect()
    try:
        for message in messages:
            if message not in late:
                sender.publish(detections_topic(1, message.camera_id), encode_message(message, 1))
        if late:
            wait_until(lambda: (store.released_timestamp() or 0) > max(
                m.timestamp for m in late), 120, "the withheld frames' windows to be released")
        for message in late:
            sender.publish(detections_topic(1, message.camera_id), encode_message(message, 1))
        wait_until(lambda: store.counters().get("processed", 0) == TOTAL - len(late)
                   + store.counters().get("late_tracked", 0)
                   and store.counters().get("late_tracked", 0) == len(late)
                   and service.drained(), 120, "every message to be tracked")
        service.close(flush=True)
        closed = True
        counters = store.counters()
    finally:
        if not closed:
            service.close()
        sender.close()
        viewer.close()
        store.close()
    return counters


@pytest.fixture(scope="module")
def undisturbed_analytics(case, tmp_path_factory) -> dict:
    """The online analytics of the service without late messages."""
    database = tmp_path_factory.mktemp("undisturbed-analytics") / "plane1.db"
    _run_item1(case, database)
    assert_undisturbed(database, case)
    analytics = _analytics_of(database)
    assert sum(value for (_, measure, _), value in analytics["counts"].items()
               if measure in ("positive", "negative")) > 0, "nobody crossed the test's line"
    return analytics


@pytest.mark.parametrize("withheld", [range(0, 3), range(20, 25)], ids=["first", "middle"])
def test_item1_late_messages_are_tracked_from_a_snapshot(case, tmp_path, withheld,
                                                         undisturbed_analytics):
    """CVLab2's messages of some frames reach the matcher only after later frames were
    released (the first frames: re-tracked from the empty tracker's snapshot; frames in the
    middle: from a snapshot before them). They are stored late, then re-tracked: every
    message is processed, the stored tracks are the undisturbed run's (exactly), the
    corrected rows are published as updates with ``corrected_from``, and the online
    analytics follow the correction: counts, bins, OD and events equal the undisturbed
    run's."""
    database = tmp_path / "plane1.db"
    updates: list[TracksUpdate] = []
    counters = _run_item1(case, database, withheld, updates)
    late_first = EPOCH + case["scene"].timestamps[withheld[0]]
    assert counters["late"] == len(withheld) and counters.get("late_untracked", 0) == 0, \
        counters
    assert counters["retracks"] >= 1 and counters["retracked"] >= len(withheld), counters
    assert "analytics_uncorrected" not in counters
    # Rows counted before the snapshot are not counted again: each row once.
    assert counters["analytics_rows"] == len(case["tracks"]), counters
    assert_undisturbed(database, case)
    corrections = [update for update in updates if update.corrected_from is not None]
    assert corrections, "no corrected update was published"
    assert max(update.corrected_from for update in corrections) < late_first
    _assert_same_analytics(_analytics_of(database), undisturbed_analytics)
