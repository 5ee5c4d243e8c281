"""Fusion tracker: where a vehicle is reported, its turning filter
(:mod:`cblrs.matching.fusion.turning`)."""

from __future__ import annotations

import json
import math

import numpy as np
from test_matching_fusion_vehicle_noise import _ring_world

from cblrs.datasets import simulate_detections
from cblrs.datasets.synthetic import SyntheticWorld
from cblrs.detections import CLASS_NAMES
from cblrs.matching.fusion.config import FusionConfig
from cblrs.matching.fusion.noise import NoiseModel
from cblrs.matching.fusion.state import table_from_state, table_state
from cblrs.matching.fusion.table import FusionContext, TrackTable
from cblrs.matching.fusion.turning import TurnFilter
from cblrs.pipeline import render_scene_references, track_scene

CAR = CLASS_NAMES.index("car")


def _context() -> FusionContext:
    config = FusionConfig()
    extra = np.array(
        [config.class_measurement_sigma_m.get(name, 0.0) for name in CLASS_NAMES] + [0.0]
    )
    return FusionContext(
        config,
        ["a", "b"],
        np.array([[0.0, 0.0], [20.0, 0.0]]),
        extra,
        np.ones(len(extra)),
        NoiseModel(0.2, 0.01),
    )


def _car(xy, velocity) -> TrackTable:
    return TrackTable(
        ids=np.array([1]),
        class_id=np.array([CAR]),
        state=np.array([[*xy, *velocity]]),
        covariance=np.diag([0.5, 0.5, 1.0, 1.0])[None],
        mode_state=np.zeros((1, 2, 4)),
        mode_covariance=np.zeros((1, 2, 4, 4)),
        mode_probability=np.full((1, 2), 0.5),
        evidence=np.ones(1, np.int64),
        last_seen=np.zeros(1),
        seen_by=np.zeros((1, 2)),
        velocity_sigma=np.ones(1),
        heading=np.array([[1.0, 0.0]]),
        heading_time=np.zeros(1),
        heading_sigma=np.zeros(1),
    )


def test_a_turning_state_moves_along_its_arc():
    turning = TurnFilter(_context())
    # 8 m/s, heading +y, turning left at 8 / 12 rad/s: a 12 m circle round the origin.
    state = np.array([[12.0, 0.0, 8.0, 0.5 * math.pi, 8.0 / 12.0], [0.0, 0.0, 5.0, 0.0, 0.0]])
    moved, covariance = turning._predict(
        state, np.zeros((2, 5, 5)), np.array([0.5, 0.5]), np.array([CAR, CAR])
    )
    angle = 0.5 * 8.0 / 12.0
    assert np.allclose(moved[0, :2], [12.0 * math.cos(angle), 12.0 * math.sin(angle)])
    assert np.isclose(moved[0, 3], 0.5 * math.pi + angle)
    assert np.allclose(moved[1, :2], [2.5, 0.0])  # no turn: a straight line
    # Speed and turn rate drift (white accelerations), and the position with them.
    assert (covariance[:, [0, 2, 4], [0, 2, 4]] > 0).all()


def test_the_filter_starts_from_the_tracker_and_again_when_a_view_cannot_be_it():
    turning = TurnFilter(_context())
    tracks = _car((0.0, 0.0), (8.0, 0.0))
    sharp = np.tile(0.01 * np.eye(2), (1, 1, 1))
    first = turning.locate(tracks, np.array([0]), np.array([[0.1, 0.0]]), sharp, 0.0)
    assert np.isfinite(tracks.turn_state).all() and tracks.turn_time[0] == 0.0
    assert np.hypot(*(first[0] - [0.1, 0.0])) < 0.1  # the sharp view, not the wide estimate
    for step in range(1, 6):
        time = 0.1 * step
        turning.locate(tracks, np.array([0]), np.array([[8.0 * time, 0.0]]), sharp, time)
    assert np.isclose(tracks.turn_state[0, 2], 8.0, atol=0.5)
    # Another vehicle 5 m to the side: the filter starts again from the tracker's estimate.
    tracks.state[0] = [4.8, 5.0, 8.0, 0.0]
    jumped = turning.locate(tracks, np.array([0]), np.array([[4.8, 5.0]]), sharp, 0.6)
    assert np.hypot(*(jumped[0] - [4.8, 5.0])) < 0.1


def test_the_turning_filters_are_saved_with_the_tracks():
    turning = TurnFilter(_context())
    tracks = _car((0.0, 0.0), (8.0, 0.0))
    turning.locate(
        tracks, np.array([0]), np.array([[0.1, 0.0]]), np.tile(0.01 * np.eye(2), (1, 1, 1)), 2.0
    )
    saved = json.loads(json.dumps(table_state(tracks)))
    restored = table_from_state(saved, 2, 2)
    assert np.array_equal(restored.turn_state, tracks.turn_state)
    assert np.array_equal(restored.turn_covariance, tracks.turn_covariance)
    assert np.array_equal(restored.turn_time, tracks.turn_time)
    for key in ("turn_state", "turn_covariance", "turn_time"):
        del saved[key]  # a state saved before this stage: no filter yet
    older = table_from_state(saved, 2, 2)
    assert np.isnan(older.turn_state).all() and np.isneginf(older.turn_time).all()


def test_a_car_on_a_ring_seen_through_jittered_boxes_is_reported_on_its_ring():
    scene = SyntheticWorld(_ring_world()).scene()
    references = render_scene_references(scene)
    boxes = simulate_detections(scene, drop=0.2, jitter=0.05, seed=1)
    tracks = track_scene(boxes, references=references).tracks
    truth = scene.ground_truth
    errors = [
        np.hypot(*(truth.world_xy[truth.frame == frame][0] - xy))
        for frame, xy in zip(tracks.frame, tracks.world_xy, strict=True)
    ]
    outwards = np.hypot(tracks.world_xy[:, 0], tracks.world_xy[:, 1]) - 12.0
    assert len(np.unique(tracks.track_id)) == 1
    # Each instant's views alone, corrected from a constant-velocity prediction: 0.25 m off
    # on average and 0.12 m outwards.
    assert np.mean(errors) < 0.2
    assert abs(np.mean(outwards)) < 0.06


def test_only_cars_are_reported_from_their_turning_filter():
    turning = TurnFilter(_context())
    classes = np.array([CAR, CLASS_NAMES.index("bus"), CLASS_NAMES.index("person"), -1])
    assert turning.applies(classes).tolist() == [True, False, False, False]


def test_a_car_that_is_not_clearly_moving_keeps_each_instant_correction():
    from test_matching_fusion_vehicle_noise import _measured, _tracks

    from cblrs.matching.fusion.vehicle_noise import VehicleNoise

    noise = VehicleNoise(_context())
    tracks = _tracks([CAR, CAR], [True, True])
    tracks.state[1, 2:] = 0.0  # stopped at a light: no heading to turn from
    world_xy = np.array([[10.1, 10.0], [10.0, 10.1]])
    assigned = np.array([0, 1])
    refined = noise.refined(tracks, np.array([CAR, CAR]), assigned)
    located = noise.locate(
        tracks,
        world_xy,
        _measured(world_xy, np.array([0, 1])),
        refined,
        np.zeros((2, 2, 2)),
        assigned,
        np.array([CAR, CAR]),
        0.0,
    )
    assert np.isfinite(located).all()
    assert np.isfinite(tracks.turn_state[0]).all() and np.isnan(tracks.turn_state[1]).all()
