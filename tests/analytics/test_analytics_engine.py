"""The analytics engine: counting rules, and online == offline whatever the chunking."""

from __future__ import annotations

import json

import numpy as np
import pytest
from analytics_helpers import random_tracks

from cblrs.analytics import (
    Analytics,
    AnalyticsConfig,
    AnalyticsError,
    HeatmapGrid,
    LineCrossing,
    ZoneEntered,
    ZoneLeft,
)
from cblrs.analytics.tables import analyse_tracks
from cblrs.detections import Tracks
from cblrs.places import CountingLine, PlaceError, Places, Zone

GATE = Places(lines=(CountingLine("gate", (0.0, -5.0), (0.0, 5.0)),))  # + = towards -x
ROOM = Places(zones=(Zone("room", [[0, 0], [10, 0], [10, 10], [0, 10]]),))


def walk(x, y=None, track=1, rate_hz=2.0, start_s=0.0, class_id=0) -> Tracks:
    x = np.asarray(x, dtype=np.float64)
    y = np.zeros_like(x) if y is None else np.asarray(y, dtype=np.float64)
    times = start_s + np.arange(len(x)) / rate_hz
    return Tracks(np.arange(len(x)), times, np.full(len(x), track), np.c_[x, y],
                  class_id=np.full(len(x), class_id))


def run_all(places, tracks, config=None):
    engine = Analytics(places, config)
    events = engine.update(tracks) + engine.flush()
    return engine, events


def crossings(events):
    return [(e.line, e.direction) for e in events if isinstance(e, LineCrossing)]


# ---------------------------------------------------------------- lines

def test_a_walk_through_the_gate_counts_once_with_time_and_place_of_the_crossing():
    _, events = run_all(GATE, walk(np.linspace(3, -3, 13), np.full(13, 1.0)))
    (event,) = events
    assert (event.direction, event.track_id, event.class_id) == ("positive", 1, 0)
    assert event.timestamp == pytest.approx(3.0)  # x = 0 at the 7th row, 2 Hz
    assert event.world_xy == pytest.approx((0.0, 1.0))


def test_jitter_across_the_line_counts_nothing_until_the_track_really_crosses():
    jitter = [0.3, -0.3] * 10  # stays inside the 0.5 m band
    x = [2.0, 1.0, *jitter, -1.0, -2.0]
    _, events = run_all(GATE, walk(x))
    assert crossings(events) == [("gate", "positive")]
    _, events = run_all(GATE, walk([2.0, *jitter, 2.0, 1.5]))
    assert crossings(events) == []


def test_without_hysteresis_the_same_jitter_counts_many_crossings():
    x = [2.0, 1.0, *([0.3, -0.3] * 10), -1.0, -2.0]
    _, events = run_all(GATE, walk(x), AnalyticsConfig(line_hysteresis_m=0.0))
    assert len(crossings(events)) == 19  # every sign change of the 20 jittered rows


def test_passing_beyond_the_segment_does_not_count_but_sets_the_side():
    # Around the north end (y = 6 > 5) to the positive side, then back through the segment.
    x = [2, 1, 0, -1, -2, -2, -1, 0, 1, 2]
    y = [6, 6, 6, 6, 6, 2, 2, 2, 2, 2]
    _, events = run_all(GATE, walk(x, y))
    assert crossings(events) == [("gate", "negative")]


SIDE_CHANGE = AnalyticsConfig(line_rule="side_change")


@pytest.mark.parametrize(
    ("case", "x", "y", "hysteresis", "side_change"),
    [
        ("a walk through", [3, 2, 1, -1, -2, -3], None, ["positive"], ["positive"]),
        # Brushing the line by centimetres: the side-change rule counts in and out.
        ("jitter", [2, 1, 0.1, -0.02, 0.1, 1, 2], None, [], ["positive", "negative"]),
        # First seen 0.3 m before the line: never farther than the hysteresis on that side.
        ("starts in the band", [0.3, -0.5, -1.5, -2.5, -3.5], None, [], ["positive"]),
        # Beyond the segment's end (y = 6 > 5): neither rule.
        ("beyond the end", [3, 2, 1, -1, -2, -3], [6] * 6, [], []),
        # Around the north end and back into the extent on the other side: a side change
        # within the extent (as supervision's LineZone counts it), no crossing of the segment.
        ("around the end", [2, 2, 1, -1, -2, -2], [2, 6, 6, 6, 6, 2], [], ["positive"]),
    ],
)
def test_the_two_line_rules(case, x, y, hysteresis, side_change):
    tracks = walk(x, y)
    _, events = run_all(GATE, tracks)
    assert [direction for _, direction in crossings(events)] == hysteresis, case
    _, events = run_all(GATE, tracks, SIDE_CHANGE)
    assert [direction for _, direction in crossings(events)] == side_change, case


def test_the_side_change_rule_is_timed_where_the_line_was_crossed_and_survives_a_restart():
    tracks = walk([3, 2, 1, -1, -2, -3], np.full(6, 1.0))
    _, events = run_all(GATE, tracks, SIDE_CHANGE)
    (event,) = events
    assert event.timestamp == pytest.approx(1.25) and event.world_xy == pytest.approx((0, 1))
    # Row by row with a state round trip in between: the same event.
    engine = Analytics(GATE, SIDE_CHANGE)
    found = []
    for index in range(len(tracks)):
        found += engine.update(tracks[np.array([index])])
        state = json.loads(json.dumps(engine.get_state()))
        engine = Analytics(GATE, SIDE_CHANGE)
        engine.set_state(state)
    assert found + engine.flush() == events
    with pytest.raises(AnalyticsError, match="other settings"):
        Analytics(GATE).set_state(state)


def test_a_line_own_rule_overrides_the_default_and_is_said_beside_its_counts():
    places = Places(lines=(CountingLine("plain", (0, -5), (0, 5), rule="side_change"),
                           CountingLine("gate", (10, -5), (10, 5))))
    jitter = walk([2, 1, 0.1, -0.02, 0.1, 1, 2])
    both = Tracks(jitter.frame, jitter.timestamp, jitter.track_id,
                  jitter.world_xy, class_id=jitter.class_id)
    result = analyse_tracks(both, places)
    counts = {(row["line"], row["direction"]): (row["count"], row["rule"])
              for row in result.lines if row["class"] == "all"}
    assert counts[("plain", "positive")] == (1, "side change within the segment's extent")
    assert counts[("gate", "positive")] == (0, "past 0.5 m each side, through the segment")
    assert Places.from_dict(places.to_dict()).to_dict() == places.to_dict()
    with pytest.raises(PlaceError, match=r"places.lines\[0\]: rule must be one of hysteresis, "
                                         r"side_change, got 'plain'"):
        Places.from_dict({"lines": [{"name": "l", "start": [0, 0], "end": [1, 0],
                                     "rule": "plain"}]})


def test_a_state_saved_before_line_rules_restores():
    engine = Analytics(GATE)
    engine.update(walk([3, 2, 1]))
    state = json.loads(json.dumps(engine.get_state()))
    del state["config"]["line_rule"]
    Analytics(GATE).set_state(state)  # counted with the hysteresis rule: the same settings


def test_a_line_own_hysteresis_overrides_the_default():
    places = Places(lines=(CountingLine("wide", (0, -5), (0, 5), hysteresis_m=2.0),))
    _, events = run_all(places, walk([1.5, 0.5, -0.5, -1.5, -1.5]))
    assert crossings(events) == []
    _, events = run_all(places, walk([2.5, 1.0, -1.0, -2.5]))
    assert crossings(events) == [("wide", "positive")]


def test_a_jump_faster_than_a_person_can_walk_is_not_a_crossing():
    _, events = run_all(GATE, walk([5, 4, 3, -3, -4, -5]))  # 6 m in 0.5 s = 12 m/s
    assert crossings(events) == []
    _, events = run_all(GATE, walk([5, 4, 3, -3, -4, -5], class_id=1))  # a car may
    assert crossings(events) == [("gate", "positive")]


def test_short_lived_ids_count_nothing_and_held_events_keep_their_times():
    short = walk([1.0, -1.0], track=7)  # 0.5 s
    _, events = run_all(GATE, short)
    assert events == []
    engine = Analytics(GATE)
    first = engine.update(walk([1.0, -1.0], track=7))
    assert first == []  # held until the track has lived min_track_s
    later = engine.update(walk([-1.5, -2.0], track=7, start_s=1.0))
    assert [(e.timestamp, e.direction) for e in later] == [(0.25, "positive")]


def test_rows_out_of_time_order_are_dropped_and_counted():
    engine = Analytics(GATE)
    engine.update(walk([3, 2, 1]))
    engine.update(walk([0], start_s=0.5))  # earlier than the clock
    assert engine.late_rows == 1


# ---------------------------------------------------------------- zones

def test_a_visit_is_timed_at_the_border_and_counted_once():
    x = np.linspace(-5, 15, 41)  # 1 m/s at 2 Hz: border at x=0 (t=5) and x=10 (t=15)
    _, events = run_all(ROOM, walk(x, np.full(41, 5.0)))
    entered = [e for e in events if isinstance(e, ZoneEntered)]
    left = [e for e in events if isinstance(e, ZoneLeft)]
    assert [(e.timestamp, e.crossed) for e in entered] == [(5.0, True)]
    assert [(e.entered_at, e.timestamp, e.dwell_s, e.entered, e.exited) for e in left] == [
        (5.0, 15.0, 10.0, True, True)
    ]


def test_flicker_at_the_border_and_short_exits_make_one_visit():
    inside, outside = 3.0, -3.0
    flicker = [0.3, -0.3] * 6  # within the 0.5 m hysteresis of the border x = 0
    brief_exit = [-1.0, -1.0, 1.0]  # out for about 1 s < merge gap
    x = [outside, -1.5, *flicker, 1.0, inside, *brief_exit, inside, 1.0, -1.0, outside, -5, -6]
    _, events = run_all(ROOM, walk(x, np.full(len(x), 5.0)))
    visits = [e for e in events if isinstance(e, ZoneLeft)]
    assert len(visits) == 1 and visits[0].entered and visits[0].exited


def test_a_long_exit_makes_two_visits_and_zone_left_waits_for_the_merge_gap():
    engine = Analytics(ROOM, AnalyticsConfig(merge_gap_s=2.0, lost_after_s=10.0))
    x = [-3, -1, 1, 3, 1, -1, -3]  # in at t=1.25, out at t=2.25
    events = engine.update(walk(x, np.full(7, 5.0)))
    assert [type(e) for e in events] == [ZoneEntered]  # the exit may still be undone
    events = engine.update(walk([-3.5], [5.0], start_s=3.5))
    assert events == []  # 1.25 s after the exit
    events = engine.update(walk([-4.0], [5.0], start_s=4.5))
    assert [(type(e), e.timestamp) for e in events] == [(ZoneLeft, 2.25)]


def test_a_track_first_seen_inside_appears_and_a_lost_track_ends_where_last_seen():
    engine, events = run_all(ROOM, walk([5, 5, 5, 5, 5], [5, 5, 5, 5, 5]))
    (entered,) = [e for e in events if isinstance(e, ZoneEntered)]
    (left,) = [e for e in events if isinstance(e, ZoneLeft)]
    assert not entered.crossed and not left.entered and not left.exited
    assert (left.entered_at, left.timestamp) == (0.0, 2.0)
    assert engine.zone_appeared[("room", 0)] == 1 and not engine.zone_entries


def test_origin_destination_and_unpaired_visits():
    places = Places(zones=(Zone("a", [[0, 0], [4, 0], [4, 4], [0, 4]]),
                           Zone("b", [[10, 0], [14, 0], [14, 4], [10, 4]])))
    x = np.linspace(-2, 16, 37)
    result = analyse_tracks(Tracks.concatenate([
        walk(x, np.full(37, 2.0), track=1),
        walk(x[::-1], np.full(37, 2.0), track=2),
        walk(x[:10], np.full(10, 2.0), track=3),  # only in a
    ]), places)
    assert result.od == {"a": {"a": 0, "b": 1}, "b": {"a": 1, "b": 0}}
    assert result.od_unpaired == {"a": 1, "b": 0}


def test_heatmap_holds_the_person_seconds_and_occupancy_integrates_to_dwell():
    grid = HeatmapGrid((-10.0, -10.0), (30.0, 30.0), 1.0)
    tracks = random_tracks(3)
    places = Places(zones=(Zone("all", [[-10, -10], [20, -10], [20, 20], [-10, 20]]),))
    config = AnalyticsConfig(heatmap=grid, interval_s=2.0, zone_hysteresis_m=0.0,
                             min_track_s=0.0, max_person_speed_m_s=1e6)
    result = analyse_tracks(tracks, places, config)
    assert result.heatmap is not None
    total = result.heatmap.sum() + result.summary["heatmap_outside_person_seconds"]
    visits = sum(v.dwell_s for v in result.visits)
    occupancy = sum(row["mean_occupancy"] * 2.0 for row in result.occupancy)
    assert occupancy == pytest.approx(visits)
    # Every step of a life (no gap longer than lost_after_s) is a person's time on the ground.
    order = np.lexsort((tracks.timestamp, tracks.track_id))
    steps = np.diff(tracks.timestamp[order])
    same = np.diff(tracks.track_id[order]) == 0
    assert total == pytest.approx(steps[same & (steps <= config.lost_after_s)].sum())


# ---------------------------------------------------------------- online == offline

def _tables(engine, events):
    return (sorted(map(repr, events)), dict(engine.line_counts), dict(engine.od),
            dict(engine.od_unpaired), dict(engine.zone_bins), dict(engine.line_bins),
            {key: round(value, 9) for key, value in engine.occupancy_seconds.items()},
            np.round(engine.heatmap, 9).tolist())


@pytest.mark.parametrize("seed", range(8))
def test_update_by_update_with_state_round_trips_equals_one_offline_pass(seed, square_places):
    tracks = random_tracks(seed)
    config = AnalyticsConfig(interval_s=3.0, heatmap=HeatmapGrid.covering((-15, -15, 15, 15)))
    whole = Analytics(square_places, config)
    expected = _tables(whole, whole.update(tracks) + whole.flush())

    engine = Analytics(square_places, config)
    events = []
    rng = np.random.default_rng(seed)
    times = np.unique(tracks.timestamp)
    cuts = np.sort(rng.choice(len(times), size=min(12, len(times)), replace=False))
    for part in np.split(times, cuts):
        if len(part) == 0:
            continue
        for instant in (part if rng.random() < 0.5 else [part]):
            rows = tracks[np.isin(tracks.timestamp, np.atleast_1d(instant))]
            events += engine.update(rows)
        state = json.loads(json.dumps(engine.get_state()))
        engine = Analytics(square_places, config)
        engine.set_state(state)
    events += engine.flush()
    assert _tables(engine, events) == expected


def test_a_saved_state_is_refused_by_other_places_or_settings(square_places):
    engine = Analytics(square_places)
    engine.update(random_tracks(0))
    state = engine.get_state()
    with pytest.raises(AnalyticsError, match="other places"):
        Analytics(GATE).set_state(state)
    with pytest.raises(AnalyticsError, match="other settings"):
        Analytics(square_places, AnalyticsConfig(merge_gap_s=9.0)).set_state(state)
    with pytest.raises(AnalyticsError, match="not a saved analytics state"):
        Analytics(square_places).set_state({"version": "x"})


def test_no_places_is_refused_with_a_sentence():
    with pytest.raises(AnalyticsError, match="the site has no places"):
        Analytics(Places())


@pytest.mark.parametrize(
    ("options", "message"),
    [({"merge_gap_s": -1.0}, "merge_gap_s must be a number >= 0"),
     ({"lost_after_s": 0.0}, "lost_after_s must be a positive number"),
     ({"interval_s": float("nan")}, "interval_s must be a positive number")],
)
def test_bad_settings_say_which(options, message):
    with pytest.raises(AnalyticsError, match=message):
        AnalyticsConfig(**options)


def test_live_occupancy_and_dwell_of_confirmed_tracks():
    engine = Analytics(ROOM)
    engine.update(walk([-2, -1, 1, 2, 3, 4], np.full(6, 5.0)))
    assert engine.live_occupancy() == {"room": 1}
    ((zone, track, seconds),) = engine.live_dwell()
    assert (zone, track) == ("room", 1) and seconds == pytest.approx(2.5 - 0.75)


@pytest.mark.parametrize("kind", ["lines only", "zones only"])
def test_a_state_round_trips_without_zones_or_without_lines(kind):
    """Slot columns of a place kind the site lacks have shape (N, 0): restored all the same."""
    places = (Places(lines=(CountingLine("gate", (0.0, -5.0), (0.0, 5.0)),))
              if kind == "lines only" else
              Places(zones=(Zone("hall", [[0.0, -5.0], [5.0, -5.0], [5.0, 5.0], [0.0, 5.0]]),)))
    walk = Tracks(np.arange(8), np.arange(8.0), np.ones(8, int),
                  np.c_[np.linspace(-4, 3, 8), np.zeros(8)])
    whole = Analytics(places)
    expected = [event.kind for event in whole.update(walk) + whole.flush()]
    first = Analytics(places)
    events = first.update(walk[:4])
    second = Analytics(places)
    second.set_state(json.loads(json.dumps(first.get_state())))
    events += second.update(walk[4:]) + second.flush()
    assert [event.kind for event in events] == expected and expected
