"""Fusion tracker: repair after assignment, a new track continuing a lost one takes its id
(:mod:`cblrs.matching.fusion.stitching`)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cblrs.detections import CLASS_NAMES, CameraMessage, Tracks
from cblrs.matching.base import MatcherError
from cblrs.matching.fusion import FusionConfig, FusionTracker, NoiseModel
from cblrs.matching.fusion.stitching import Stitching
from cblrs.matching.fusion.table import FusionContext, TrackTable
from cblrs.plane import PlaneSet, PlaneSpec

CAR = CLASS_NAMES.index("car")
PERSON = CLASS_NAMES.index("person")


def stage(**options) -> Stitching:
    config = FusionConfig(**options)
    context = FusionContext(
        config,
        ["a", "b"],
        np.full((2, 2), np.nan),
        np.zeros(len(CLASS_NAMES) + 1),
        np.ones(len(CLASS_NAMES) + 1),
        NoiseModel(0.2, 0.03),
    )
    return Stitching(context, np.full(len(CLASS_NAMES) + 1, config.acceleration_sigma))


def rows(
    at,
    velocity,
    *,
    ids=1,
    class_id=PERSON,
    last_seen=10.0,
    born=None,
    position_sigma=0.2,
    velocity_sigma=0.15,
) -> TrackTable:
    """Tracks at ``at`` (K, 2) moving at ``velocity`` (K, 2), one motion model each."""
    at = np.asarray(at, float).reshape(-1, 2)
    velocity = np.asarray(velocity, float).reshape(-1, 2)
    count = len(at)
    state = np.hstack([at, velocity])
    covariance = np.tile(np.diag([position_sigma**2] * 2 + [velocity_sigma**2] * 2), (count, 1, 1))
    return TrackTable(
        ids=np.broadcast_to(np.asarray(ids, np.int64), (count,)).copy(),
        class_id=np.full(count, class_id, np.int64),
        state=state,
        covariance=covariance,
        mode_state=state[:, None].copy(),
        mode_covariance=covariance[:, None].copy(),
        mode_probability=np.ones((count, 1)),
        evidence=np.full(count, 10),
        last_seen=np.full(count, last_seen),
        seen_by=np.full((count, 2), last_seen),
        velocity_sigma=np.full(count, velocity_sigma * np.sqrt(2.0)),
        heading=np.zeros((count, 2)),
        heading_time=np.full(count, -np.inf),
        heading_sigma=np.zeros(count),
        born=np.full(count, last_seen if born is None else born),
    )


def one_model(**options) -> dict:
    return {"model_acceleration_factors": (1.0,), "model_sojourn_s": (1.0,), **options}


def lost_walker(stitching: Stitching, dropped_at: float = 12.0) -> None:
    """A person last seen at 10 s at (0, 0) walking east at 1.2 m/s, dropped at 12 s (the
    tracker's prediction then: (2.4, 0))."""
    stitching.remember(rows([2.4, 0.0], [1.2, 0.0], ids=7, last_seen=10.0), dropped_at)


def test_a_new_track_where_a_lost_walker_went_takes_its_id():
    stitching = stage(**one_model())
    lost_walker(stitching)
    # Born at 12.5 s at (3.0, 0.1), decided at 13.0 s: 1.2 m/s east.
    fresh = rows([3.6, 0.1], [1.2, 0.05], ids=-1, last_seen=13.0, born=12.5)
    stitches = stitching.decide(fresh, np.array([True]), 13.0)
    assert stitches.rows.tolist() == [0] and stitches.ids.tolist() == [7]
    assert not stitches.hold.any()
    # The id is taken: a second new track there later is not given it too.
    again = rows([4.8, 0.1], [1.2, 0.0], ids=-1, last_seen=14.0, born=13.5)
    assert stitching.decide(again, np.array([True]), 14.0).rows.tolist() == []


@pytest.mark.parametrize(
    ("case", "fresh"),
    [
        ("walking back", dict(at=[3.0, 0.1], velocity=[-1.2, 0.0])),
        ("far from where it went", dict(at=[3.6, 3.5], velocity=[1.2, 0.0])),
        ("standing", dict(at=[3.0, 0.1], velocity=[0.0, 0.0])),
    ],
)
def test_a_new_track_unlike_the_lost_one_gets_a_new_id(case, fresh):
    stitching = stage(**one_model())
    lost_walker(stitching)
    new = rows(**fresh, ids=-1, last_seen=13.5, born=12.5)
    stitches = stitching.decide(new, np.array([True]), 13.5)
    assert stitches.rows.tolist() == [], case
    assert not stitches.hold.any(), case


def test_a_new_track_clearly_moving_is_decided_at_once():
    stitching = stage(**one_model())
    lost_walker(stitching)
    back = rows([3.0, 0.1], [-1.2, 0.0], ids=-1, last_seen=12.6, born=12.5)
    stitches = stitching.decide(back, np.array([True]), 12.6)
    assert not stitches.hold.any() and stitches.rows.tolist() == []


def test_a_car_on_the_opposite_lane_does_not_continue_a_lost_car():
    """Car A drove north at 8 m/s and was lost; car B appears 3.5 m across, heading south."""
    stitching = stage(**one_model())
    stitching.remember(
        rows(
            [0.0, 16.0],
            [0.0, 8.0],
            ids=3,
            class_id=CAR,
            last_seen=10.0,
            position_sigma=0.7,
            velocity_sigma=0.5,
        ),
        12.0,
    )
    south = rows(
        [-3.5, 16.0],
        [0.0, -8.0],
        ids=-1,
        class_id=CAR,
        last_seen=13.0,
        born=12.5,
        position_sigma=0.7,
        velocity_sigma=0.5,
    )
    assert stitching.decide(south, np.array([True]), 13.0).rows.tolist() == []
    north = rows(
        [0.0, 24.0],
        [0.0, 8.0],
        ids=-1,
        class_id=CAR,
        last_seen=13.0,
        born=12.5,
        position_sigma=0.7,
        velocity_sigma=0.5,
    )
    assert stitching.decide(north, np.array([True]), 13.0).ids.tolist() == [3]


def test_a_new_track_whose_velocity_is_unknown_is_held_at_most_the_delay():
    stitching = stage(**one_model(stitch_delay_s=1.0))
    lost_walker(stitching)
    young = rows([3.0, 0.0], [0.0, 0.0], ids=-1, last_seen=12.5, born=12.5, velocity_sigma=1.5)
    assert stitching.decide(young, np.array([True]), 12.5).hold.tolist() == [True]
    # Still unsure of its velocity after the delay: confirmed with a new id.
    late = stitching.decide(young, np.array([True]), 13.5)
    assert not late.hold.any() and late.rows.tolist() == []
    # Nothing lost near it: never held.
    elsewhere = rows([3.0, 9.0], [0.0, 0.0], ids=-1, last_seen=12.5, born=12.5, velocity_sigma=1.5)
    assert not stitching.decide(elsewhere, np.array([True]), 12.5).hold.any()


def test_two_new_tracks_that_could_both_continue_a_lost_one_are_left_apart():
    stitching = stage(**one_model())
    lost_walker(stitching)
    both = rows(
        [[3.6, 0.3], [3.6, -0.3]], [[1.2, 0.0], [1.2, 0.0]], ids=-1, last_seen=13.0, born=12.5
    )
    stitches = stitching.decide(both, np.array([True, True]), 13.0)
    assert stitches.rows.tolist() == []


def test_two_lost_tracks_a_new_one_could_continue_are_left_apart():
    stitching = stage(**one_model())
    stitching.remember(
        rows([[2.4, 0.3], [2.4, -0.3]], [[1.2, 0.0], [1.2, 0.0]], ids=[7, 8], last_seen=10.0), 12.0
    )
    fresh = rows([3.6, 0.0], [1.2, 0.0], ids=-1, last_seen=13.0, born=12.5)
    assert stitching.decide(fresh, np.array([True]), 13.0).rows.tolist() == []


def coasting_walker(fresh_at, fresh_born: float = 11.4) -> TrackTable:
    """Row 0: a confirmed person (id 7) last seen at 10 s at (0, 0) walking east at 1.2 m/s,
    still coasting at 12 s (predicted at (2.4, 0)); row 1: a new track born at ``fresh_born``
    at ``fresh_at``, its velocity not known yet."""
    walker = rows([2.4, 0.0], [1.2, 0.0], ids=7, last_seen=10.0, position_sigma=0.5)
    fresh = rows(fresh_at, [0.0, 0.0], ids=-1, last_seen=12.0, born=fresh_born,
                 velocity_sigma=1.5)
    return walker.extend(fresh)


def test_a_new_track_near_a_coasting_persons_prediction_takes_its_id_and_replaces_it():
    # The person turned while no camera saw them: they reappear 1.2 m off the prediction,
    # and two cameras confirm the new track before its velocity is known.
    table = coasting_walker([2.0, 1.1])
    coasting = np.array([True, False])
    stitches = stage(**one_model()).decide(table, np.array([False, True]), 12.0, coasting)
    assert stitches.rows.tolist() == [1] and stitches.ids.tolist() == [7]
    assert stitches.replaced.tolist() == [0]
    # Off, or no coasting track given (only dropped ones count): a new id.
    off = stage(**one_model(stitch_coasting=False))
    assert off.decide(table, np.array([False, True]), 12.0, coasting).rows.tolist() == []
    assert stage(**one_model()).decide(table, np.array([False, True]), 12.0).rows.tolist() == []


@pytest.mark.parametrize(
    ("case", "fresh_at", "fresh_born"),
    [
        ("seen while the person still was", [2.0, 1.1], 9.5),
        ("farther than the coasting track could have gone", [2.4, 5.0], 11.4),
    ],
)
def test_a_new_track_unlike_a_coasting_one_gets_a_new_id(case, fresh_at, fresh_born):
    table = coasting_walker(fresh_at, fresh_born)
    stitches = stage(**one_model()).decide(table, np.array([False, True]), 12.0,
                                           np.array([True, False]))
    assert stitches.rows.tolist() == [] and stitches.replaced.tolist() == [], case


def turned_walker(fresh_velocity) -> TrackTable:
    """Row 0: a confirmed person (id 7) last seen at 10 s at (0, 0) walking east at 1.2 m/s,
    still coasting at 12 s (predicted at (2.4, 0)); row 1: a new track born at 11.4 s, now at
    (1.53, 1.53), where a quarter turn to the left at 1.2 m/s over the 2 s ends, moving at
    ``fresh_velocity`` (clearly known)."""
    walker = rows([2.4, 0.0], [1.2, 0.0], ids=7, last_seen=10.0)
    walker.seen_covariance = walker.covariance[:, :2, :2].copy()
    fresh = rows([1.53, 1.53], fresh_velocity, ids=-1, last_seen=12.0, born=11.4)
    return walker.extend(fresh)


def test_a_walker_who_turned_while_hidden_keeps_the_id():
    # 1.8 m off the prediction and heading north, not east: neither the gate test nor the
    # reach of a change of velocity holds; the arc of a quarter turn does.
    table = turned_walker([0.0, 1.2])
    confirmable, coasting = np.array([False, True]), np.array([True, False])
    stitches = stage(**one_model()).decide(table, confirmable, 12.0, coasting)
    assert stitches.rows.tolist() == [1] and stitches.ids.tolist() == [7]
    assert stitches.replaced.tolist() == [0]
    off = stage(**one_model(stitch_turn_dps=0.0))
    assert off.decide(table, confirmable, 12.0, coasting).rows.tolist() == []


@pytest.mark.parametrize(
    ("case", "velocity"),
    [("heading south: the arc to the right ends 3 m away", [0.0, -1.2]),
     ("twice as fast", [0.0, 2.4])],
)
def test_a_new_track_off_the_turned_walkers_arc_gets_a_new_id(case, velocity):
    stitches = stage(**one_model()).decide(turned_walker(velocity), np.array([False, True]),
                                           12.0, np.array([True, False]))
    assert stitches.rows.tolist() == [], case


def test_two_coasting_tracks_a_new_one_could_continue_are_left_apart():
    table = coasting_walker([2.0, 1.1])
    other = rows([2.4, 1.6], [1.2, 0.0], ids=8, last_seen=10.0, position_sigma=0.5)
    table = table.extend(other)
    stitches = stage(**one_model()).decide(table, np.array([False, True, False]), 12.0,
                                           np.array([True, False, True]))
    assert stitches.rows.tolist() == []


def test_only_tracks_born_after_the_lost_one_was_last_seen_and_within_the_gap():
    stitching = stage(**one_model(stitch_gap_s=3.0, stitch_delay_s=1.0))
    lost_walker(stitching)
    # Seen at 9.5 s, while the walker still was: another person.
    before = rows([3.6, 0.0], [1.2, 0.0], ids=-1, last_seen=13.0, born=9.5)
    assert stitching.decide(before, np.array([True]), 13.0).rows.tolist() == []
    # Born 3.5 s after it was last seen: and nothing can continue it any more.
    late = rows([6.0, 0.0], [1.2, 0.0], ids=-1, last_seen=14.0, born=13.5)
    assert len(stitching.lost) == 1
    assert stitching.decide(late, np.array([True]), 14.0).rows.tolist() == []
    assert len(stitching.lost) == 0


def test_a_lost_track_waits_past_the_gap_for_a_new_track_born_within_it():
    """A new track can stay tentative for a while (a second camera must confirm it)."""
    stitching = stage(**one_model())
    lost_walker(stitching)
    waiting = rows([6.0, 0.0], [1.2, 0.0], ids=-1, last_seen=15.0, born=12.5)
    assert stitching.decide(waiting, np.array([False]), 15.0).rows.tolist() == []
    assert len(stitching.lost) == 1
    assert stitching.decide(waiting, np.array([True]), 15.0).ids.tolist() == [7]


def test_tentative_tracks_and_a_zero_gap_are_not_remembered():
    stitching = stage(stitch_gap_s=0.0)
    lost_walker(stitching)
    assert len(stitching.lost) == 0
    fresh = rows([3.6, 0.1], [1.2, 0.0], ids=-1, last_seen=13.0, born=12.5)
    assert stitching.decide(fresh, np.array([True]), 13.0).rows.tolist() == []
    stitching = stage()
    stitching.remember(rows([2.4, 0.0], [1.2, 0.0], ids=-1), 12.0)
    assert len(stitching.lost) == 0


@pytest.mark.parametrize("name", ["stitch_gap_s", "stitch_delay_s", "stitch_sigmas"])
def test_stitching_options_are_checked(name):
    with pytest.raises(MatcherError, match=name):
        FusionConfig(**{name: -1.0})


def test_stitch_coasting_must_be_true_or_false():
    with pytest.raises(MatcherError, match="stitch_coasting"):
        FusionConfig(stitch_coasting="yes")


# ------------------------------------------------------------------ the whole tracker

PLANES = PlaneSet([PlaneSpec(1, (-20.0, -20.0), 40.0, 40.0)])
CAMERAS = {"west": (-25.0, 0.0), "east": (25.0, 0.0)}


def message(camera: str, frame: int, points, class_id: int = PERSON) -> CameraMessage:
    points = np.asarray(points, float).reshape(-1, 2)
    colour, valid = PLANES[0].encode(points)
    colour = colour[valid]
    count = len(colour)
    boxes = np.tile([0.0, 0.0, 40.0, 30.0], (count, 1))
    return CameraMessage(
        camera,
        frame,
        frame * 0.1,
        frame,
        boxes,
        np.ones(count),
        np.full(count, class_id, np.int64),
        colour.astype(np.int64),
    )


def hidden_walk(frame: int) -> list[list[float]]:
    """A person walking east at 1.2 m/s who nobody sees from 2 s to 4.6 s (behind a
    kiosk), and after it veers slightly: the coasting track's gate misses them."""
    time = frame * 0.1
    if 2.0 <= time < 4.6:
        return []
    position = [-10.0 + 1.2 * time, 0.0]
    if time >= 4.6:
        position[1] = 0.35 * (time - 3.0)
    return [position]


def track_walk(frames: range, tracker: FusionTracker) -> list[Tracks]:
    return [
        tracker.update(frame * 0.1, [message(name, frame, hidden_walk(frame)) for name in CAMERAS])
        for frame in frames
    ]


def test_a_person_hidden_for_seconds_keeps_one_id_and_no_row_is_rewritten():
    def tracks(**options) -> Tracks:
        tracker = FusionTracker(PLANES, list(CAMERAS), camera_positions=CAMERAS, **options)
        return Tracks.concatenate(track_walk(range(80), tracker))

    apart = tracks(stitch_gap_s=0.0)
    assert len(np.unique(apart.track_id)) == 2  # lost for 2.6 s > max_age_s: a new id
    # Two cameras confirm the new track at once, before its velocity is known: by default
    # (no delay) it cannot be told from someone else and keeps its new id.
    assert len(np.unique(tracks().track_id)) == 2
    # Held back up to a second, its velocity settles and matches: one id. The held rows are
    # not reported (never relabelled afterwards).
    stitched = tracks(stitch_delay_s=1.0)
    assert np.unique(stitched.track_id).tolist() == [1]
    assert 0 < len(apart) - len(stitched) <= 10  # decided once moving: at most 1 s, 10 fps


def turning_walk(frame: int) -> list[list[float]]:
    """A person walking east at 1.2 m/s whom nobody sees from 2 s to 3 s (hidden behind
    others), who turned north meanwhile: they reappear 1.8 m off the coasting track's
    prediction, within max_age_s."""
    time = frame * 0.1
    if 2.0 <= time < 3.0:
        return []
    if time < 2.0:
        return [[-10.0 + 1.2 * time, 0.0]]
    return [[-7.6, 1.2 * (time - 2.0)]]


def test_a_person_who_turned_while_hidden_keeps_their_id_from_the_coasting_track():
    def tracks(miss_rate: float, **options) -> Tracks:
        tracker = FusionTracker(PLANES, list(CAMERAS), camera_positions=CAMERAS, **options)
        # The occlusion stage's learnt rate: these cameras miss people hidden behind others.
        tracker.hidden.occluded_views, tracker.hidden.occluded_missed = 100.0, 100.0 * miss_rate
        return Tracks.concatenate([
            tracker.update(frame * 0.1, [message(name, frame, turning_walk(frame))
                                         for name in CAMERAS])
            for frame in range(60)])

    stitched = tracks(0.9)
    assert np.unique(stitched.track_id).tolist() == [1]
    # Off, or where the cameras see people through occlusion (a person missed by every
    # camera has left): the new track keeps its new id. No row is lost either way.
    apart = tracks(0.9, stitch_coasting=False)
    assert np.unique(apart.track_id).tolist() == [1, 2]
    assert np.unique(tracks(0.01).track_id).tolist() == [1, 2]
    assert len(stitched) == len(apart)


def test_lost_tracks_are_part_of_the_saved_state():
    def tracker() -> FusionTracker:
        return FusionTracker(PLANES, list(CAMERAS), camera_positions=CAMERAS, stitch_delay_s=1.0)

    undisturbed, first = tracker(), tracker()
    expected = track_walk(range(80), undisturbed)
    assert len(np.unique(Tracks.concatenate(expected).track_id)) == 1
    got = track_walk(range(45), first)  # dropped at 4.0 s, not seen again yet
    state = json.loads(json.dumps(first.get_state()))
    assert len(state["stitching"]["ids"]) == 1
    restored = tracker()
    restored.set_state(state)
    got += track_walk(range(45, 80), restored)
    for ours, theirs in zip(got, expected, strict=True):
        np.testing.assert_array_equal(ours.track_id, theirs.track_id)
        np.testing.assert_array_equal(ours.world_xy, theirs.world_xy)
    # A state saved before the stage existed restores with nothing lost.
    state.pop("stitching")
    older = tracker()
    older.set_state(state)
    assert len(older.stitching.lost) == 0
