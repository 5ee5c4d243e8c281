"""Online analytics with the matcher's store: restarts anywhere count exactly like one pass,
out-of-order rows within the delay count right, later ones are counted as late, and the
store keeps classes and opens files written before the class column."""

from __future__ import annotations

import sqlite3
from dataclasses import replace

import numpy as np
import pytest

from cblrs.analytics import AnalyticsError, analyse_tracks, load_site_places
from cblrs.datasets import load_scene
from cblrs.detections import Tracks
from cblrs.places import CountingLine, Places, Zone
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.analytics_store import (
    count_summary,
    read_bins,
    read_counts,
    read_events,
    read_od,
)
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics, plane_places

EPOCH = 1_700_000_000.0
REPO_SITE = "sites/wildtrack.yaml"


@pytest.fixture(scope="module")
def truth(wildtrack_root):
    tracks = load_scene(wildtrack_root).ground_truth
    return replace(tracks, timestamp=tracks.timestamp + EPOCH)


@pytest.fixture(scope="module")
def places():
    from pathlib import Path

    return load_site_places(Path(__file__).resolve().parents[2] / REPO_SITE).places


def run_online(tracks: Tracks, places: Places, store: RuntimeStore, restart_every: int = 0,
               flush: bool = True) -> None:
    """Feed ``tracks`` group by group (one group per capture time), committing each group;
    with ``restart_every`` a new engine resumes from the store that often (a restart)."""
    online = OnlineAnalytics(places)
    times = np.unique(tracks.timestamp)
    for index, timestamp in enumerate(times):
        if restart_every and index % restart_every == restart_every - 1:
            online = OnlineAnalytics(places)
            assert online.resume(store) == (index > 0)
        rows = tracks[tracks.timestamp == timestamp]
        online.update(rows, float(timestamp))
        store.commit_group([], rows, None, float(timestamp), {}, also=online.take_writes())
    if flush:
        online.flush()
        store.commit_group([], Tracks.empty(), None, float(times[-1]), {},
                           also=online.take_writes())


def check_equal_offline(store: RuntimeStore, tracks: Tracks, places: Places) -> None:
    offline = analyse_tracks(tracks, places)
    counts = count_summary(read_counts(store))
    for row in offline.lines:
        if row["class"] == "all":
            assert counts["lines"].get(row["line"], {}).get(row["direction"], 0) == row["count"]
    for row in offline.zones:
        zone = counts["zones"].get(row["zone"], {})
        for measure in ("entries", "appeared", "exits", "visits"):
            assert zone.get(measure, 0) == row[measure], (row["zone"], measure)
        if row["visits"]:
            assert zone["mean_dwell_s"] == pytest.approx(row["mean_dwell_s"], abs=1e-9)
    od = {(o, d): n for o, row in offline.od.items() for d, n in row.items() if n}
    assert read_od(store) == od
    events = read_events(store)
    assert len(events) == (len(offline.crossings) + len(offline.visits)
                           + sum(row["entries"] + row["appeared"] for row in offline.zones))


@pytest.mark.parametrize("restart_every", [0, 1, 7, 50])
def test_restarts_anywhere_count_like_one_offline_pass(truth, places, tmp_path, restart_every):
    store = RuntimeStore(tmp_path / "m.db")
    run_online(truth, places, store, restart_every)
    check_equal_offline(store, truth, places)
    counters = store.counters()
    assert counters["analytics_rows"] == len(truth) and "analytics_late_rows" not in counters
    # Running totals in the events are the counts in emission order.
    crossings = [event.body for event in read_events(store) if event.body["kind"] == "line_crossed"]
    last: dict[tuple[str, str], int] = {}
    for body in crossings:
        key = (body["place"], body["direction"])
        assert body["total"] == last.get(key, 0) + 1
        last[key] = body["total"]
    store.close()


def test_the_state_stays_small_however_long_it_runs(truth, places, tmp_path):
    store = RuntimeStore(tmp_path / "m.db")
    run_online(truth, places, store, flush=False)
    import json

    state = store.get_meta("analytics_state")
    engine = state["engine"]
    assert engine["visits"] == [] and engine["line_counts"] == [] and engine["line_bins"] == []
    assert len(json.dumps(state)) < 60_000
    store.close()


def test_rows_out_of_order_within_the_delay_count_later_ones_are_late(tmp_path):
    places = Places(lines=(CountingLine("gate", (0.0, -5.0), (0.0, 5.0)),))
    walk = Tracks(np.arange(10), np.arange(10.0), np.ones(10, int),
                  np.c_[np.linspace(-4.5, 4.5, 10), np.zeros(10)])
    online = OnlineAnalytics(places, delay_s=1.0)
    # Row 5 arrives one group late (within the delay), row 3 after everything.
    events = []
    for t in range(10):
        rows = walk[(walk.timestamp == t) & (walk.timestamp != 5) & (walk.timestamp != 3)]
        if t == 6:
            rows = Tracks.concatenate([rows, walk[walk.timestamp == 5]])
        events += online.update(rows, float(t))
    events += online.update(walk[walk.timestamp == 3], 9.0)
    events += online.flush()
    assert [event.kind for event in events] == ["line_crossed"]
    writes = online.take_writes()
    assert writes.counters["analytics_late_rows"] == 1
    assert writes.counters["analytics_rows"] == 9


def test_state_of_other_places_is_refused_with_one_sentence(truth, places, tmp_path):
    store = RuntimeStore(tmp_path / "m.db")
    run_online(truth[truth.timestamp < EPOCH + 5], places, store, flush=False)
    other = Places(lines=(CountingLine("gate", (0.0, -5.0), (0.0, 5.0)),))
    with pytest.raises(AnalyticsError, match=r"other places\. Keep the site's places"):
        OnlineAnalytics(other).resume(store)
    with pytest.raises(AnalyticsError, match="another delay"):
        OnlineAnalytics(places, delay_s=2.0).resume(store)
    store.close()


def test_plane_places_keep_their_plane_and_shared_ones():
    places = Places(
        zones=(Zone("a", [[0, 0], [1, 0], [1, 1]], plane_id=1),
               Zone("b", [[0, 0], [1, 0], [1, 1]], plane_id=2),
               Zone("c", [[0, 0], [1, 0], [1, 1]])),
        lines=(CountingLine("l", (0, 0), (1, 0), plane_id=2),),
    )
    assert plane_places(places, 1).names == ["a", "c"]
    assert plane_places(places, 2).names == ["b", "c", "l"]


def test_no_places_and_heatmaps_are_refused():
    from cblrs.analytics import AnalyticsConfig, HeatmapGrid

    with pytest.raises(AnalyticsError, match="no places"):
        OnlineAnalytics(Places())
    places = Places(lines=(CountingLine("gate", (0.0, -5.0), (0.0, 5.0)),))
    with pytest.raises(AnalyticsError, match="no heatmap"):
        OnlineAnalytics(places, AnalyticsConfig(heatmap=HeatmapGrid((0, 0), (1, 1))))
    with pytest.raises(AnalyticsError, match="delay"):
        OnlineAnalytics(places, delay_s=-1)


def test_store_keeps_track_classes_and_opens_files_without_the_column(tmp_path):
    path = tmp_path / "old.db"
    connection = sqlite3.connect(path)
    connection.executescript(
        "CREATE TABLE tracks (row INTEGER PRIMARY KEY AUTOINCREMENT, frame INTEGER NOT NULL, "
        "timestamp REAL NOT NULL, track_id INTEGER NOT NULL, x REAL NOT NULL, y REAL NOT NULL, "
        "camera INTEGER NOT NULL, x_min REAL, y_min REAL, x_max REAL, y_max REAL);"
        "INSERT INTO tracks (frame, timestamp, track_id, x, y, camera) "
        "VALUES (0, 1.0, 3, 0.5, 0.5, -1);"
    )
    connection.commit()
    connection.close()
    store = RuntimeStore(path)
    assert store.tracks().class_id.tolist() == [-1]
    rows = Tracks(np.array([1, 1]), np.array([2.0, 2.0]), np.array([3, 4]),
                  np.array([[1.0, 1.0], [2.0, 2.0]]), class_id=np.array([1, -1]))
    store.commit_group([], rows, None, 2.0)
    assert store.tracks().class_id.tolist() == [-1, 1, -1]
    assert store.tracks(after_row=1).track_id.tolist() == [3, 4]
    store.close()


@pytest.mark.parametrize(
    "clocks",
    [
        {"offset_s": 0.3, "jitter_s": 0.01, "seed": 1},
        {"offset_s": 0.3, "camera_fps": (2.0, 1.0), "drop": 0.05, "seed": 2},
    ],
)
def test_unsynchronised_cameras_count_like_offline(wildtrack_root, places, clocks):
    """Cameras with their own clocks and rates, windowed as the service does: the tracker
    returns rows up to half a second behind a window's time; the online counts wait for
    them and equal one offline pass over the same rows."""
    from cblrs.datasets.clocks import ClockSimulation
    from cblrs.matching import make_matcher
    from cblrs.pipeline import (
        camera_messages,
        camera_positions,
        ordered_windows,
        render_scene_references,
    )

    scene = load_scene(wildtrack_root).select_frames(0, 995)
    references = render_scene_references(scene)
    matcher = make_matcher("fusion", references[0].planes, scene.camera_names,
                           camera_positions=camera_positions(scene))
    online = OnlineAnalytics(places)
    parts, counts, late, lag = [], {}, 0, 0.0

    def take() -> None:
        nonlocal late
        writes = online.take_writes()
        late += writes.counters.get("analytics_late_rows", 0)
        for key, value in writes.counts.items():
            counts[key] = counts.get(key, 0) + value

    windows = ordered_windows(
        camera_messages(scene, references, None, ClockSimulation(**clocks)), scene.camera_names)
    for timestamp, messages in windows:
        rows = matcher.update(timestamp, messages)
        if len(rows):
            lag = max(lag, timestamp - float(rows.timestamp.min()))
        parts.append(rows)
        online.update(rows, timestamp)
        take()
    rows = matcher.flush()
    parts.append(rows)
    online.update(rows, timestamp)
    online.flush()
    take()
    offline = analyse_tracks(Tracks.concatenate(parts), places)
    assert lag > 0.2, "the tracker returned no earlier rows: the case tests nothing"
    assert late == 0
    for row in offline.lines:
        if row["class"] == "all":
            online_count = sum(value for (line, direction, _), value in counts.items()
                               if (line, direction) == (row["line"], row["direction"]))
            assert online_count == row["count"], row
    for row in offline.zones:
        for measure in ("entries", "exits", "visits"):
            online_count = sum(value for (zone, name, _), value in counts.items()
                               if (zone, name) == (row["zone"], measure))
            assert online_count == row[measure], (row["zone"], measure)


def test_retention_deletes_old_published_events_and_bins_and_keeps_the_totals(tmp_path):
    import time

    from cblrs.runtime.matcher.retention import RetentionPolicy, apply_retention
    from cblrs.runtime.outputs.analytics_store import mark_published

    places = Places(lines=(CountingLine("gate", (0.0, -5.0), (0.0, 5.0)),))
    store = RuntimeStore(tmp_path / "m.db")
    now = time.time()
    for start in (now - 3 * 86400, now - 600):  # one walk three days ago, one ten minutes ago
        walk = Tracks(np.arange(8), start + np.arange(8.0), np.full(8, int(start) % 1000),
                      np.c_[np.linspace(-4, 3, 8), np.zeros(8)])
        online = OnlineAnalytics(places)
        if start > now - 86400:
            online.resume(store)
        online.update(walk, start + 7)
        online.flush()
        store.commit_group([], walk, None, start + 7, {}, also=online.take_writes())
    events = read_events(store)
    assert len(events) == 2
    mark_published(store, [events[1].id])  # the old one is not published yet
    deleted = apply_retention(store, RetentionPolicy(max_age_s=86400, max_bytes=None), now)
    assert [event.id for event in read_events(store)] == [event.id for event in events]
    assert deleted["count_bins"] >= 1 and deleted.get("events", 0) == 0
    assert min(start for start, *_ in read_bins(store)) > now - 86400
    mark_published(store, [events[0].id])
    deleted = apply_retention(store, RetentionPolicy(max_age_s=86400, max_bytes=None), now)
    assert deleted["events"] == 1
    assert [event.id for event in read_events(store)] == [events[1].id]
    assert count_summary(read_counts(store))["lines"]["gate"]["negative"] == 2  # totals kept
    store.close()
