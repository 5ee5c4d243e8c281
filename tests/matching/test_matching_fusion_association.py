"""Fusion tracker: association of detections to tracks
(:mod:`cblrs.matching.fusion.association`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from fusion_scenes import (
    CAMERA_XY,
    CAMERAS,
    PLANES,
    camera_message,
)

from cblrs.matching import FusionTracker
from cblrs.matching.base import decode_messages
from cblrs.matching.fusion import (
    assign_per_camera,
)
from cblrs.matching.fusion.association import _merge_assignments


def test_assignment_is_per_camera_and_optimal():
    # Detections 0, 1 from camera 0 and detection 2 from camera 1; two tracks.
    rows = np.array([0, 0, 1, 2])
    columns = np.array([0, 1, 0, 0])
    cost = np.array([1.0, 1.5, 0.2, 0.1])
    assigned = assign_per_camera(rows, columns, cost, np.array([0, 0, 1]), 2)
    # Camera 0: detection 1 takes track 0 (0.2), so detection 0 gets track 1 (total 1.7 <
    # 1.0 + nothing); camera 1's detection also takes track 0 (a different camera).
    assert assigned.tolist() == [1, 0, 0]
    empty = assign_per_camera(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0),
                              np.array([0]), 1)
    assert empty.tolist() == [-1]


def test_assignment_may_leave_a_detection_unassigned_when_that_is_more_likely():
    """Detection 0 fits track 0 well and track 1 badly; detection 1 only fits track 0.

    The most pairs (0 -> 1, 1 -> 0) cost 15 + 3 = 18; detection 0 -> track 0 with
    detection 1 left unassigned (at cost 10) costs 11: the most likely assignment.
    """
    rows, columns, cost = np.array([0, 0, 1]), np.array([0, 1, 0]), np.array([1.0, 15.0, 3.0])
    camera = np.zeros(2, np.int64)
    assert assign_per_camera(rows, columns, cost, camera, 1).tolist() == [1, 0]
    unassigned = np.array([10.0, 10.0])
    assert assign_per_camera(rows, columns, cost, camera, 1, unassigned).tolist() == [0, -1]
    # A lone pair dearer than leaving its detection alone is not taken either.
    lone = assign_per_camera(np.array([0]), np.array([0]), np.array([12.0]), camera[:1], 1,
                             unassigned[:1])
    assert lone.tolist() == [-1]


@pytest.mark.parametrize("group_radius_m", [0.7, 0.0])
def test_side_by_side_walkers_are_not_blended(group_radius_m):
    """Two people 0.5 m apart, each camera missing one of them now and then."""
    rng = np.random.default_rng(7)
    tracker = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY,
                            group_radius_m=group_radius_m)
    outputs = []
    for frame in range(40):
        timestamp = frame * 0.5
        truth = np.array([[1.0 + 1.2 * timestamp, 2.0], [1.0 + 1.2 * timestamp, 2.5]])
        messages = []
        for camera in CAMERAS:
            seen = rng.random(2) > 0.25
            messages.append(camera_message(camera, frame, timestamp, truth[seen], rng, 0.03))
        output = tracker.update(timestamp, messages)
        for track_id, position in zip(output.track_id.tolist(), output.world_xy, strict=True):
            outputs.append((track_id, np.abs(position[1] - truth[:, 1]).min()))
    assert {track_id for track_id, _ in outputs} == {1, 2}
    assert max(error for _, error in outputs) < 0.15


@pytest.mark.parametrize(
    ("best", "candidate", "best_track", "candidate_track", "detection_cost", "expected"),
    [
        # Detections 0, 1 swap tracks 0, 1 (one group); the candidate is cheaper there.
        ([0, 1, 2], [1, 0, 2], [5.0, 5.0, 1.0], [2.0, 2.0, 1.0], [9.0] * 3, [1, 0, 2]),
        # ... and dearer: the best one stays.
        ([0, 1, 2], [1, 0, 2], [2.0, 2.0, 1.0], [5.0, 5.0, 1.0], [9.0] * 3, [0, 1, 2]),
        # Two independent groups: each takes its own cheaper assignment.
        ([0, 1, 2, 3], [1, 0, 3, 2], [5.0, 5.0, 1.0, 1.0], [2.0, 2.0, 3.0, 3.0], [9.0] * 4,
         [1, 0, 2, 3]),
        # The candidate leaves detection 1 out (its cost 9 counts against it).
        ([0, 1], [0, -1], [1.0, 4.0], [1.0, 0.0], [9.0, 9.0], [0, 1]),
        ([0, 1], [0, -1], [1.0, 12.0], [1.0, 0.0], [9.0, 9.0], [0, -1]),
        # Nothing to merge.
        ([], [], [], [], [], []),
    ],
)
def test_merge_assignments_keeps_the_cheaper_one_per_group(
    best, candidate, best_track, candidate_track, detection_cost, expected
):
    best, candidate = np.array(best, np.int64), np.array(candidate, np.int64)
    detection_cost = np.array(detection_cost)
    best_detection = np.where(best < 0, detection_cost, 0.0)
    candidate_detection = np.where(candidate < 0, detection_cost, 0.0)
    merged = _merge_assignments(
        best, candidate, np.flatnonzero(best != candidate), np.array(best_track),
        best_detection, np.array(candidate_track), candidate_detection,
    )
    np.testing.assert_array_equal(merged, expected)


def test_more_camera_orders_never_explain_an_instant_less_likely():
    """The assignment kept from several camera orders is at least as likely as the first's."""
    rng = np.random.default_rng(3)
    tracker = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY, group_radius_m=0.0,
                            association_orders=3)
    start = rng.uniform(2, 8, size=(12, 2))
    velocity = rng.uniform(-1.0, 1.0, size=(12, 2))  # m/s: everyone stays on the plane
    improved = 0
    for frame in range(16):
        timestamp = frame * 0.5
        truth = start + velocity * timestamp
        messages = [
            camera_message(camera, frame, timestamp, truth[rng.random(len(truth)) > 0.2], rng,
                           0.25)
            for camera in CAMERAS
        ]
        tracker._predict(timestamp)  # update() below predicts by 0 s again: no change
        observed = decode_messages(tracker.planes, tracker._cameras, messages)
        covariance = tracker._measurement_covariance(observed)
        costs = {}
        for orders in (1, 3):
            tracker.context.config = dataclasses.replace(tracker.config,
                                                         association_orders=orders)
            assigned = tracker.association.associate(tracker.tracks, tracker.measured,
                                                     observed, covariance)
            track_cost, detection_cost = tracker.association.joint_cost(
                tracker.tracks, tracker.measured, observed, covariance, assigned,
                list(range(len(CAMERAS))),
            )
            costs[orders] = track_cost.sum() + detection_cost.sum()
        assert costs[3] <= costs[1] + 1e-6
        improved += costs[3] < costs[1] - 1e-6
        tracker.update(timestamp, messages)
    assert improved > 0  # the scene is crowded enough for the orders to disagree

