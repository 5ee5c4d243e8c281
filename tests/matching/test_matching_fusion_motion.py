"""Fusion tracker: vehicles cannot turn on the spot, tracks that leave end, multi-view
confirmation (:mod:`cblrs.matching.fusion.motion`, :mod:`~cblrs.matching.fusion.coverage`)."""

from __future__ import annotations

import json

import numpy as np

from cblrs.detections import CLASS_NAMES, CameraMessage, Tracks
from cblrs.matching.base import Observations
from cblrs.matching.fusion import FusionConfig, FusionTracker, NoiseModel
from cblrs.matching.fusion.coverage import Coverage
from cblrs.matching.fusion.motion import MotionCheck
from cblrs.matching.fusion.table import FusionContext, TrackTable
from cblrs.plane import PlaneSet, PlaneSpec

CAR = CLASS_NAMES.index("car")
PERSON = CLASS_NAMES.index("person")


def context(**options) -> FusionContext:
    config = FusionConfig(**options)
    return FusionContext(config, ["a", "b"], np.full((2, 2), np.nan),
                         np.zeros(len(CLASS_NAMES) + 1), np.ones(len(CLASS_NAMES) + 1),
                         NoiseModel(0.2, 0.03))


def one_track(class_id: int, velocity=(0.0, 6.0), last_seen=10.0, at=(2.0, 33.0),
              velocity_sigma=0.5) -> TrackTable:
    table = TrackTable.empty(models=2, cameras=2)
    row = TrackTable(
        ids=np.array([1]), class_id=np.array([class_id]),
        state=np.array([[*at, *velocity]]), covariance=np.eye(4)[None] * 4.0,
        mode_state=np.zeros((1, 2, 4)), mode_covariance=np.zeros((1, 2, 4, 4)),
        mode_probability=np.full((1, 2), 0.5), evidence=np.array([20]),
        last_seen=np.array([last_seen]), seen_by=np.full((1, 2), last_seen),
        velocity_sigma=np.array([velocity_sigma]), heading=np.zeros((1, 2)),
        heading_time=np.array([-np.inf]), heading_sigma=np.zeros(1),
        # Its position was well estimated when last seen; the prediction since is not.
        seen_covariance=np.eye(2)[None] * 0.1,
    )
    return table.extend(row)


def detections(points) -> tuple[Observations, np.ndarray]:
    points = np.asarray(points, float)
    count = len(points)
    observed = Observations(
        world_xy=points, colour=np.zeros((count, 3), np.int64),
        camera=np.arange(count) % 2, xyxy=np.tile([0.0, 0.0, 10.0, 10.0], (count, 1)),
        confidence=np.ones(count), class_id=np.full(count, CAR, np.int64),
    )
    return observed, np.tile(np.eye(2) * 0.09, (count, 1, 1))


def test_a_car_cannot_take_a_detection_on_the_opposite_lane_behind_it():
    # Last seen at (2, 30.6) driving north at 6 m/s, 0.4 s ago; predicted at (2, 33).
    check = MotionCheck(context())
    tracks = one_track(CAR, at=(2.0, 33.0), last_seen=10.0)
    opposite, covariance = detections([[-2.0, 30.0], [-1.8, 30.1]])
    released = check.check(tracks, opposite, covariance, np.array([0, 0]), 10.4)
    assert released.tolist() == [-1, -1]
    ahead, covariance = detections([[2.1, 32.8], [1.9, 33.1]])
    assert check.check(tracks, ahead, covariance, np.array([0, 0]), 10.4).tolist() == [0, 0]


def test_people_and_vehicles_of_unknown_speed_are_not_limited():
    check = MotionCheck(context())
    opposite, covariance = detections([[-2.0, 30.0]])
    person = one_track(PERSON, velocity=(0.0, 1.4))
    assert check.check(person, opposite, covariance, np.array([0]), 10.4).tolist() == [0]
    unsure = one_track(CAR, velocity_sigma=3.0)  # speed 6 is not three sigmas above zero
    assert check.check(unsure, opposite, covariance, np.array([0]), 10.4).tolist() == [0]


def test_split_flags_a_car_whose_direction_reversed_sooner_than_it_can_turn():
    check = MotionCheck(context())
    tracks = one_track(CAR, velocity=(0.0, 6.0), velocity_sigma=0.3)
    seen = np.array([True])
    assert not check.split(tracks, seen, 10.0).any()  # first well-known heading: recorded
    tracks.state[0, 2:4] = (0.3, 6.0)
    assert not check.split(tracks, seen, 10.1).any()  # a gentle turn
    tracks.state[0, 2:4] = (0.0, -6.0)
    assert check.split(tracks, seen, 10.6).tolist() == [True]  # reversed in half a second


def test_coverage_counts_cameras_that_see_a_place():
    planes = PlaneSet([PlaneSpec(1, (0.0, 0.0), 10.0, 10.0)])
    coverage = Coverage(planes, camera_count=3, covering_count=2)
    coverage.learn(np.array([[1.2, 1.2], [1.4, 1.1], [1.3, 1.3], [1.2, 1.4]]),
                   np.array([0, 0, 1, 1]))
    coverage.learn(np.array([[8.0, 8.0]]), np.array([2]))
    assert coverage.covering(np.array([[1.5, 1.5], [8.0, 8.0], [50.0, 5.0]])).tolist() == [
        2, 0, 0]
    coverage.set_view(2, np.array([[1.1, 1.9], [8.0, 8.0]]))  # told: camera 2 sees these
    assert coverage.covering(np.array([[1.5, 1.5], [8.0, 8.0]])).tolist() == [3, 1]


PLANES = PlaneSet([PlaneSpec(1, (-20.0, -20.0), 40.0, 40.0)])


def message(camera: str, frame: int, points, class_id: int = CAR) -> CameraMessage:
    points = np.asarray(points, float).reshape(-1, 2)
    colour, valid = PLANES[0].encode(points)
    colour = colour[valid]
    count = len(colour)
    boxes = np.tile([0.0, 0.0, 40.0, 30.0], (count, 1))
    return CameraMessage(camera, frame, frame * 0.1, frame, boxes, np.ones(count),
                         np.full(count, class_id, np.int64), colour.astype(np.int64))


def test_a_car_leaving_is_not_handed_the_next_car_arriving_on_the_opposite_lane():
    """Car A drives north off the plane; car B enters 3.5 m away heading south just after."""
    def run(**options) -> Tracks:
        tracker = FusionTracker(PLANES, ["west", "east"], **options,
                                camera_positions={"west": (-25.0, 0.0), "east": (25.0, 0.0)})
        parts = []
        for frame in range(60):
            t = frame * 0.1
            points = []
            a = np.array([1.75, 6.0 + 6.0 * t])
            if a[1] < 20.0:
                points.append(a)
            if t >= 2.6:
                points.append([-1.75, 19.5 - 6.0 * (t - 2.6)])
            messages = [message(name, frame, points) for name in ("west", "east")]
            parts.append(tracker.update(t, messages))
        parts.append(tracker.flush())
        return Tracks.concatenate(parts)

    def one_id_for_both(tracks: Tracks) -> bool:
        first = tracks.track_id[tracks.world_xy[:, 0] > 0]
        second = tracks.track_id[(tracks.world_xy[:, 0] < 0) & (tracks.timestamp > 3.0)]
        assert len(first) and len(second)
        return not set(first.tolist()).isdisjoint(second.tolist())

    assert not one_id_for_both(run())
    # Either rule alone separates them; without both, the coasting track takes car B.
    assert not one_id_for_both(run(class_turn_radius_m={}))
    assert not one_id_for_both(run(end_off_plane=False))
    assert one_id_for_both(run(end_off_plane=False, class_turn_radius_m={}))


def test_a_false_positive_one_camera_keeps_seeing_where_two_see_is_never_confirmed():
    tracker = FusionTracker(PLANES, ["west", "east"],
                            camera_positions={"west": (-25.0, 0.0), "east": (25.0, 0.0)})
    both = np.array([[x, y] for x in np.arange(-19.5, 20, 1.0) for y in np.arange(-19.5, 20, 1.0)])
    tracker.coverage.set_view(0, both)
    tracker.coverage.set_view(1, both)
    parts = []
    for frame in range(30):
        person = [[-5.0 + 0.12 * frame, 0.0]]
        messages = [message("west", frame, [*person, [6.0, 6.0]], PERSON),
                    message("east", frame, person, PERSON)]
        parts.append(tracker.update(frame * 0.1, messages))
    tracks = Tracks.concatenate(parts)
    assert len(np.unique(tracks.track_id)) == 1  # the person, not the west camera's ghost
    assert np.all(np.abs(tracks.world_xy[:, 1]) < 1.0)


def test_learned_coverage_is_part_of_the_saved_state():
    """A matcher restarted from its saved state confirms as the undisturbed one: what the
    coverage grid learnt travels with the state (not the views, which are configuration)."""
    def tracker() -> FusionTracker:
        return FusionTracker(PLANES, ["west", "east"],
                             camera_positions={"west": (-25.0, 0.0), "east": (25.0, 0.0)})

    def messages(frame: int) -> list[CameraMessage]:
        # People walking where both cameras see them (the grid learns that); from frame 40
        # the west camera alone keeps seeing a ghost on ground both have located people on.
        people = [[-5.0 + 0.12 * frame, 0.0]]
        if frame < 40:  # a second person walks through the ghost's place, then leaves
            people.append([6.0, -6.0 + 0.3 * frame])
        ghost = [[6.0, 3.0]] if frame >= 40 else []
        return [message("west", frame, [*people, *ghost], PERSON),
                message("east", frame, people, PERSON)]

    undisturbed, first = tracker(), tracker()
    expected = [undisturbed.update(frame * 0.1, messages(frame)) for frame in range(70)]
    got = [first.update(frame * 0.1, messages(frame)) for frame in range(35)]
    state = first.get_state()
    assert state["coverage"]["cells"] and max(state["coverage"]["counts"]) == 3
    restored = tracker()
    restored.set_state(json.loads(json.dumps(state)))
    assert restored.coverage.covering(np.array([[6.0, 3.0]])).tolist() == [2]
    got += [restored.update(frame * 0.1, messages(frame)) for frame in range(35, 70)]
    for ours, theirs in zip(got, expected, strict=True):
        np.testing.assert_array_equal(ours.track_id, theirs.track_id)
        np.testing.assert_array_equal(ours.world_xy, theirs.world_xy)
    # The ghost was never confirmed; without the learnt grid a restarted tracker would have.
    def ghost_rows(parts: list[Tracks]) -> int:
        tracks = Tracks.concatenate(parts)
        return int(((tracks.timestamp >= 4.0) & (tracks.world_xy[:, 1] > 2.0)).sum())

    assert ghost_rows(got) == 0
    forgetful = tracker()
    saved = dict(state)
    saved.pop("coverage")
    forgetful.set_state(json.loads(json.dumps(saved)))
    assert ghost_rows([forgetful.update(frame * 0.1, messages(frame))
                       for frame in range(35, 70)]) > 0


def test_a_moving_track_one_camera_sees_where_two_see_is_confirmed():
    """The other camera is told it sees the place but does not see the car (an occluder its
    reference image does not know): the car moves, so one camera confirms it; the same car
    parked is never confirmed, and with the exception off neither is the moving one."""
    def ids(speed: float, **options) -> int:
        tracker = FusionTracker(PLANES, ["west", "east"], **options,
                                camera_positions={"west": (-25.0, 0.0), "east": (25.0, 0.0)})
        both = np.array([[x, y] for x in np.arange(-19.5, 20, 1.0)
                         for y in np.arange(-19.5, 20, 1.0)])
        tracker.coverage.set_view(0, both)
        tracker.coverage.set_view(1, both)
        parts = [tracker.update(frame * 0.1, [
            message("west", frame, [[-10.0 + speed * frame * 0.1, 2.0]]),
            message("east", frame, [])]) for frame in range(30)]
        return len(np.unique(Tracks.concatenate(parts).track_id))

    assert ids(6.0) == 1
    assert ids(0.0) == 0
    assert ids(6.0, confirm_moving_mps=0.0) == 0
