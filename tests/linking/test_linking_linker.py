"""PlaneLinker: one global id across planes, in any chunking, across restarts."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cblrs.datasets.city import city_scenes, street_world
from cblrs.detections import Tracks
from cblrs.linking import PlaneLink
from cblrs.linking.linker import LinkedRows, LinkerConfig, PlaneLinker, link_tracks
from cblrs.plane import PlaneSet, PlaneSpec

WEST, EAST = PlaneSpec(1, (0, 0), 40, 30), PlaneSpec(2, (34, 0), 40, 30)
FAR = PlaneSpec(3, (90, 0), 40, 30)
PLANES = PlaneSet([WEST, EAST, FAR])
PORTALS = ([[68, 0], [74, 0], [74, 30], [68, 30]], [[90, 0], [96, 0], [96, 30], [90, 30]])
LINKS = (PlaneLink.overlap(WEST, EAST), PlaneLink.through_portals((2, 3), PORTALS, (0, 30)))
TIMES = np.round(np.arange(0, 80, 0.1), 3)


def walk(start_x: float, y: float, speed: float, start_s: float = 0.0):
    """(T, 2) positions of someone walking along x (NaN before they start)."""
    xy = np.c_[start_x + speed * (TIMES - start_s), np.full(len(TIMES), y)]
    xy[TIMES < start_s] = np.nan
    return xy


def seen(xy, plane: PlaneSpec, track: int, class_id: int = 0, noise: float = 0.0, seed=0):
    """The rows a plane's matcher gives for positions on it."""
    on = np.isfinite(xy[:, 0]) & plane.contains(np.nan_to_num(xy, nan=-1e9))
    rng = np.random.default_rng(seed)
    positions = xy[on] + rng.normal(0, noise, size=(int(on.sum()), 2))
    return Tracks(np.flatnonzero(on), TIMES[on], np.full(int(on.sum()), track), positions,
                  class_id=np.full(int(on.sum()), class_id))


def ids_of(rows: LinkedRows) -> list[int]:
    return sorted(set(rows.tracks.track_id.tolist()))


def test_someone_walking_through_an_overlap_keeps_one_id_and_one_row_per_instant():
    person = walk(20, 10, 1.3)
    rows, handovers, counters = link_tracks(PLANES, LINKS, {1: seen(person, WEST, 7),
                                                           2: seen(person, EAST, 3)})
    assert ids_of(rows) == [1]
    frames = rows.tracks.frame
    assert len(frames) == len(set(frames.tolist()))  # the overlap's rows are not doubled
    expected = np.flatnonzero(WEST.contains(person) | EAST.contains(person))
    np.testing.assert_array_equal(frames, expected)
    [handover] = handovers
    assert (handover.from_plane, handover.from_track, handover.to_plane, handover.to_track,
            handover.kind) == (1, 7, 2, 3, "overlap")
    # In the band the row comes from the plane that sees it deeper inside its rectangle.
    band = rows.plane_id[(rows.tracks.world_xy[:, 0] > 34) & (rows.tracks.world_xy[:, 0] < 40)]
    assert set(band.tolist()) == {1, 2}
    assert counters["rows_shared"] > 0


def test_a_portal_hands_over_when_the_time_fits_the_speed():
    person = walk(50, 12, 1.25)  # 68..74 -> 90..96: 16 m unseen, about 13 s
    person[(person[:, 0] > 74) & (person[:, 0] < 90)] = np.nan
    rows, handovers, _ = link_tracks(PLANES, LINKS, {2: seen(person, EAST, 4),
                                                    3: seen(person, FAR, 9)})
    assert ids_of(rows) == [1] and [item.kind for item in handovers] == ["portal"]
    # Someone arriving 15 s later than the 13 s the walk takes (still within the portal's
    # 30 s) is someone else: over 3 units of max(1 s, 30 % of 13 s).
    left = float(TIMES[np.flatnonzero(np.isfinite(person[:, 0]) & (person[:, 0] <= 74))[-1]])
    other = walk(90, 12, 1.25, start_s=left + 28.0)
    rows, handovers, _ = link_tracks(PLANES, LINKS, {2: seen(person, EAST, 4),
                                                    3: seen(other, FAR, 9)})
    assert ids_of(rows) == [1, 2] and handovers == []


def test_a_portal_transit_beyond_its_longest_is_a_new_id():
    slow = walk(66, 12, 0.4)  # 16 m at 0.4 m/s: 40 s > 30 s
    slow[(slow[:, 0] > 74) & (slow[:, 0] < 90)] = np.nan
    rows, handovers, _ = link_tracks(PLANES, LINKS, {2: seen(slow, EAST, 4),
                                                    3: seen(slow, FAR, 9)})
    assert handovers == [] and len(ids_of(rows)) == 2


def test_two_people_side_by_side_keep_their_own_ids_and_classes_do_not_mix():
    left, right = walk(20, 10, 1.3), walk(20, 12.5, 1.3)
    per_plane = {1: Tracks.concatenate([seen(left, WEST, 1, noise=0.1, seed=1),
                                        seen(right, WEST, 2, noise=0.1, seed=2)]),
                 2: Tracks.concatenate([seen(right, EAST, 5, noise=0.1, seed=3),
                                        seen(left, EAST, 6, noise=0.1, seed=4)])}
    rows, handovers, _ = link_tracks(PLANES, LINKS, per_plane)
    pairs = {(item.from_track, item.to_track) for item in handovers}
    assert pairs == {(1, 6), (2, 5)}
    # A car where the person was: not the person.
    car = seen(left, EAST, 6, class_id=1)
    rows, handovers, _ = link_tracks(PLANES, LINKS, {1: seen(left, WEST, 1), 2: car})
    assert handovers == [] and len(ids_of(rows)) == 2


def test_tracks_away_from_any_link_leave_at_once_and_watched_ones_within_the_decision():
    linker = PlaneLinker(PLANES, LINKS)
    inside = walk(5, 5, 0.5)  # plane 1, far from the band
    linker.push(1, seen(inside, WEST, 1)[:50])
    out = linker.advance(float(TIMES[49]))
    assert len(out) == 50 and out.tracks.timestamp.max() == TIMES[49]
    linker = PlaneLinker(PLANES, LINKS)
    arriving = walk(36, 20, 0.5)  # starts in the band: watched for 1 s
    linker.push(2, seen(arriving, EAST, 1)[:30])
    assert len(linker.advance(float(TIMES[5]))) == 0 and linker.watching == 1
    out = linker.advance(float(TIMES[29]))
    assert linker.watching == 0 and len(out) == 30


def test_rows_older_than_what_was_linked_are_counted_late():
    linker = PlaneLinker(PLANES, LINKS)
    rows = seen(walk(5, 5, 0.5), WEST, 1)
    linker.push(1, rows[10:20])
    linker.advance(float(TIMES[19]))
    assert linker.push(1, rows[:15]) == 15
    assert linker.counters["late_rows"] == 15
    assert len(linker.finish()) == 0


@pytest.mark.parametrize(
    "change", [{"decision_s": -1.0}, {"forget_after_s": 0.5}, {"velocity_weight_s": float("nan")}]
)
def test_bad_settings_are_refused(change):
    with pytest.raises(ValueError):
        replace(LinkerConfig(), **change)


@pytest.fixture(scope="module")
def city_tracks():
    """The small city's planes seen as matchers would number them: every plane's ground
    truth with its own track ids, 5 cm of noise and a few dropped rows."""
    city = city_scenes(street_world(seed=2, people=10, cars=4, wanderers=1, spawn_s=6.0,
                                    max_trip_m=90.0))
    rng = np.random.default_rng(0)
    per_plane = {}
    for plane_id, scene in city.planes.items():
        truth = scene.ground_truth
        keep = rng.random(len(truth)) > 0.05
        noisy = replace(truth[keep], track_id=truth.track_id[keep] * 10 + plane_id,
                        world_xy=truth.world_xy[keep] + rng.normal(0, 0.05, (int(keep.sum()), 2)))
        per_plane[plane_id] = noisy[np.argsort(noisy.timestamp, kind="stable")]
    return city, per_plane


def test_the_city_links_to_its_true_identities(city_tracks):
    city, per_plane = city_tracks
    rows, handovers, counters = link_tracks(city.spec.planes, city.spec.links, per_plane)
    truth = city.ground_truth
    # Every global id is one object, every object one global id.
    local_to_object = rows.local_track_id // 10
    pairs = set(zip(rows.tracks.track_id.tolist(), local_to_object.tolist(), strict=True))
    assert len(pairs) == len({g for g, _ in pairs}) == len({o for _, o in pairs})
    assert len(pairs) == len(np.unique(truth.track_id))
    assert {item.kind for item in handovers} == {"overlap", "portal"}
    assert counters.get("late_rows", 0) == 0


def test_any_chunking_with_restarts_gives_the_offline_rows(city_tracks):
    city, per_plane = city_tracks
    offline, offline_handovers, _ = link_tracks(city.spec.planes, city.spec.links, per_plane)
    rng = np.random.default_rng(5)
    end = max(float(tracks.timestamp.max()) for tracks in per_plane.values())
    linker = PlaneLinker(city.spec.planes, city.spec.links)
    parts, handovers = [], []
    cursor = {plane: 0 for plane in per_plane}
    watermark = 0.0
    while watermark < end:
        watermark = min(end, watermark + float(rng.uniform(0.05, 3.0)))
        for plane, tracks in per_plane.items():
            stop = int(np.searchsorted(tracks.timestamp, watermark, side="right"))
            linker.push(plane, tracks[cursor[plane]:stop])
            cursor[plane] = stop
        parts.append(linker.advance(watermark))
        handovers += linker.take_handovers()
        if rng.random() < 0.3:  # a restart: the state through JSON into a new linker
            state = json.loads(json.dumps(linker.get_state()))
            linker = PlaneLinker(city.spec.planes, city.spec.links)
            linker.set_state(state)
    parts.append(linker.finish())
    handovers += linker.take_handovers()
    online = LinkedRows.concatenate(parts)
    for name in ("frame", "timestamp", "track_id", "world_xy", "class_id"):
        np.testing.assert_array_equal(getattr(online.tracks, name), getattr(offline.tracks, name))
    np.testing.assert_array_equal(online.plane_id, offline.plane_id)
    assert handovers == offline_handovers
    assert np.all(np.diff(online.tracks.timestamp) >= 0)
