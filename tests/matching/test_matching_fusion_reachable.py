"""Fusion tracker: the reachable cone of a vehicle track, in the association gate and the
motion check (:mod:`cblrs.matching.fusion.reachable`)."""

from __future__ import annotations

import json

import numpy as np

from cblrs.detections import CLASS_NAMES, CameraMessage, Tracks
from cblrs.matching.base import Observations
from cblrs.matching.fusion import FusionConfig, FusionTracker, NoiseModel
from cblrs.matching.fusion.gaussian import largest_sigma
from cblrs.matching.fusion.reachable import ReachableCone
from cblrs.matching.fusion.state import table_from_state, table_state
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable
from cblrs.plane import PlaneSet, PlaneSpec

CAR = CLASS_NAMES.index("car")
PERSON = CLASS_NAMES.index("person")


def cone() -> ReachableCone:
    config = FusionConfig()
    return ReachableCone(
        FusionContext(
            config,
            ["a"],
            np.full((1, 2), np.nan),
            np.zeros(len(CLASS_NAMES) + 1),
            np.ones(len(CLASS_NAMES) + 1),
            NoiseModel(0.2, 0.03),
        )
    )


def along_road(count: int, along_sigma: float = 1.9, across_sigma: float = 0.3) -> np.ndarray:
    """(count, 2, 2) covariances of views looking along a north-south road."""
    return np.tile(np.diag([across_sigma**2, along_sigma**2]), (count, 1, 1))


def one_track(
    class_id: int, velocity=(0.0, 6.0), last_seen=10.0, at=(2.0, 31.2), velocity_sigma=0.5
) -> TrackTable:
    return TrackTable.empty(models=2, cameras=1).extend(
        TrackTable(
            ids=np.array([1]),
            class_id=np.array([class_id]),
            state=np.array([[*at, *velocity]]),
            covariance=np.diag([0.1, 0.1, 0.25, 0.25])[None],
            mode_state=np.zeros((1, 2, 4)),
            mode_covariance=np.zeros((1, 2, 4, 4)),
            mode_probability=np.full((1, 2), 0.5),
            evidence=np.array([20]),
            last_seen=np.array([last_seen]),
            seen_by=np.full((1, 1), last_seen),
            velocity_sigma=np.array([velocity_sigma]),
            heading=np.zeros((1, 2)),
            heading_time=np.array([-np.inf]),
            heading_sigma=np.zeros(1),
        )
    )


def test_the_distance_outside_the_cone_is_measured_in_the_noise_across_its_edge():
    reach = cone()
    anchor, heading = np.array([[2.0, 30.0]] * 3), np.array([[0.0, 1.0]] * 3)
    limit = np.full(3, 0.1)
    points = np.array([[2.1, 31.2], [-2.0, 30.2], [2.0, 27.0]])  # ahead, beside, behind
    sigmas = reach.outside(anchor, heading, limit, points, along_road(3))
    assert sigmas[0] == 0.0
    # 4 m to the side: 0.3 m across the road makes it ~13 sigma out, although it is only
    # ~2 of the views' largest (along-road) standard deviations away.
    assert sigmas[1] > 10.0
    gap = sigmas[1] * np.hypot(0.3, FusionConfig().object_sigma_m)  # metres
    largest = largest_sigma(along_road(1) + reach.context.object_covariance)[0]
    assert gap / largest < FusionConfig().gate_sigmas  # inside the gate by that measure
    # Behind the apex the nearest point is the apex, 3 m away along the road: 1.6 sigma.
    np.testing.assert_allclose(sigmas[2], 3.0 / np.hypot(1.9, 0.1), rtol=1e-6)


def test_only_moving_vehicles_are_limited():
    reach = cone()
    beside = np.array([[-2.0, 30.2]])
    columns = np.array([0])
    car = one_track(CAR)
    assert reach.feasible(car, 10.2, columns, beside, along_road(1)).tolist() == [False]
    assert reach.feasible(car, 10.2, columns, np.array([[2.0, 31.3]]), along_road(1)).tolist() == [
        True
    ]
    person = one_track(PERSON, velocity=(0.0, 1.4))
    assert reach.feasible(person, 10.2, columns, beside, along_road(1)).tolist() == [True]
    unsure = one_track(CAR, velocity_sigma=3.0)  # 6 m/s is not three sigmas above zero
    assert reach.feasible(unsure, 10.2, columns, beside, along_road(1)).tolist() == [True]
    stopped = one_track(CAR, velocity=(0.0, 0.5), velocity_sigma=0.1)
    assert reach.feasible(stopped, 10.2, columns, beside, along_road(1)).tolist() == [True]


def test_a_track_whose_motion_is_no_longer_well_known_keeps_its_last_known_cone():
    """A wrong view dragged the track sideways and its velocity is uncertain now; it is still
    held to the cone of the motion it had when that was well known."""
    reach = cone()
    car = one_track(CAR, velocity=(-2.0, 3.0), velocity_sigma=2.5, at=(0.5, 31.5))
    columns, beside = np.array([0]), np.array([[-2.0, 30.5]])
    assert reach.feasible(car, 10.2, columns, beside, along_road(1)).tolist() == [True]
    car.heading[0], car.heading_time[0], car.heading_sigma[0] = (0.0, 1.0), 9.9, 0.05
    car.heading_xy[0], car.heading_speed[0] = (2.0, 30.4), 6.0
    assert reach.feasible(car, 10.2, columns, beside, along_road(1)).tolist() == [False]
    ahead = np.array([[2.1, 32.2]])
    assert reach.feasible(car, 10.2, columns, ahead, along_road(1)).tolist() == [True]
    # Long after, the path it can have driven allows any direction.
    assert reach.feasible(car, 15.0, columns, beside, along_road(1)).tolist() == [True]


PLANES = PlaneSet([PlaneSpec(1, (-20.0, -40.0), 40.0, 80.0)])


def message(camera: str, frame: int, points) -> CameraMessage:
    points = np.asarray(points, float).reshape(-1, 2)
    colour, valid = PLANES[0].encode(points)
    colour = colour[valid]
    count = len(colour)
    boxes = np.tile([0.0, 0.0, 60.0, 40.0], (count, 1))
    return CameraMessage(
        camera,
        frame,
        frame * 0.1,
        frame,
        boxes,
        np.ones(count),
        np.full(count, CAR, np.int64),
        colour.astype(np.int64),
    )


def test_a_coasting_car_keeps_its_id_while_an_oncoming_car_passes():
    """Car A drives north; its views are missed for 0.6 s just as car B appears 3.5 m to the
    side of A's prediction and drives south past it. Both cameras look along the road (masts
    at its two ends), so each view is metres uncertain along the road but precise across it.
    (Before the reachable cone, B's views took A's track and A came back with a new id.)"""
    tracker = FusionTracker(
        PLANES,
        ["south", "north"],
        camera_positions={"south": (0.0, -45.0, 10.0), "north": (0.0, 45.0, 10.0)},
    )
    parts = []
    for frame in range(60):
        t = frame * 0.1
        points = []
        a = (1.75, -15.0 + 6.0 * t)
        if not 2.5 <= t < 3.1:  # car A missed
            points.append(a)
        if t >= 2.55:  # car B appears 3.5 m to the side of A's prediction, driving south
            points.append((-1.75, 0.3 + 1.0 - 6.0 * (t - 2.55)))
        parts.append(
            tracker.update(t, [message(name, frame, points) for name in ("south", "north")])
        )
    parts.append(tracker.flush())
    tracks = Tracks.concatenate(parts)
    car_a = tracks.track_id[tracks.world_xy[:, 0] > 0]
    car_b = tracks.track_id[tracks.world_xy[:, 0] < 0]
    assert len(car_a) and len(car_b)
    assert len(np.unique(car_a)) == 1  # A coasted through and kept its id
    assert set(car_a.tolist()).isdisjoint(car_b.tolist())  # B never took it
    before = tracks.timestamp[tracks.track_id == car_a[0]]
    assert before.min() < 2.5 and before.max() > 3.0


def test_the_association_gate_leaves_a_detection_a_coasting_car_cannot_reach():
    """A single view beside a coasting car, within its positional gate: given the window's
    time the association does not offer it to the car (it starts its own track)."""
    tracker = FusionTracker(
        PLANES, ["south"], camera_positions={"south": (0.0, -45.0, 10.0)}, group_radius_m=0.0
    )
    tracker.tracks = one_track(CAR, at=(1.75, 0.6), last_seen=9.8)
    tracker.tracks.covariance[0] = np.diag([1.0, 1.0, 0.25, 0.25])
    for points, expected in (([[-1.75, 0.0]], [-1]), ([[1.8, 0.5]], [0])):
        observed = Observations(
            world_xy=np.array(points, float),
            colour=np.zeros((1, 3), np.int64),
            camera=np.zeros(1, np.int64),
            xyxy=np.array([[0.0, 0.0, 60.0, 40.0]]),
            confidence=np.ones(1),
            class_id=np.array([CAR]),
        )
        covariance = along_road(1, along_sigma=1.5, across_sigma=0.4)
        by_position = tracker.association.associate(
            tracker.tracks,
            Measured(np.array([45.0]), np.array([45.0]), np.array([[0.0, 1.0]]), np.array([1.5])),
            observed,
            covariance,
        )
        assert by_position.tolist() == [0]  # within 4 sigma of the prediction either way
        by_motion = tracker.association.associate(
            tracker.tracks,
            Measured(np.array([45.0]), np.array([45.0]), np.array([[0.0, 1.0]]), np.array([1.5])),
            observed,
            covariance,
            timestamp=10.0,
        )
        assert by_motion.tolist() == expected


def test_what_the_cone_needs_travels_with_the_saved_state():
    car = one_track(CAR)
    car.heading[0], car.heading_time[0], car.heading_sigma[0] = (0.0, 1.0), 9.9, 0.05
    car.heading_xy[0], car.heading_speed[0] = (2.0, 30.4), 6.0
    car.seen_covariance[0] = [[0.2, 0.05], [0.05, 0.3]]
    saved = json.loads(json.dumps(table_state(car)))
    restored = table_from_state(saved, models=2, cameras=1)
    for mine, theirs in zip(car.columns(), restored.columns(), strict=True):
        np.testing.assert_array_equal(mine, theirs)
    # A state saved before these columns: no motion recorded, the prediction's covariance.
    for key in ("heading_xy", "heading_speed", "seen_covariance"):
        saved.pop(key)
    old = table_from_state(saved, models=2, cameras=1)
    assert np.isnan(old.heading_xy).all() and old.heading_speed.tolist() == [0.0]
    np.testing.assert_array_equal(old.seen_covariance, car.covariance[:, :2, :2])
