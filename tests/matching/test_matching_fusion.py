"""The fusion tracker on synthetic messages: fusion across cameras, gaps, timing, state."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from cblrs.detections import CameraMessage, Tracks
from cblrs.matching import FusionTracker, MatcherError, kalman, make_matcher
from cblrs.matching.base import decode_messages
from cblrs.matching.fusion import (
    NoiseModel,
    _merge_assignments,
    assign_per_camera,
    cluster_detections,
    fuse,
    inverse_cholesky_2x2,
    ray_covariance,
)
from cblrs.plane import PlaneSet, PlaneSpec

PLANES = PlaneSet([PlaneSpec(1, (-10.0, -10.0), 40.0, 40.0)])
CAMERAS = ["north", "east", "south"]
CAMERA_XY = {"north": (5.0, 22.0), "east": (22.0, 5.0), "south": (5.0, -12.0)}


def walkers(times: np.ndarray) -> np.ndarray:
    """(F, 3, 2) positions of three people walking straight lines, 2 m apart or more."""
    start = np.array([[0.0, 0.0], [4.0, 6.0], [10.0, 2.0]])
    velocity = np.array([[1.2, 0.3], [-0.8, 0.9], [0.2, -1.1]])
    return start[None] + times[:, None, None] * velocity[None]


def camera_message(camera: str, frame: int, timestamp: float, points: np.ndarray,
                   rng: np.random.Generator, noise_m: float = 0.05) -> CameraMessage:
    noisy = points + rng.normal(0.0, noise_m, size=points.shape)
    colour, valid = PLANES[0].encode(noisy.reshape(-1, 2))
    assert valid.all()
    count = len(colour)
    boxes = np.column_stack([np.arange(count) * 50.0, np.zeros(count),
                             np.arange(count) * 50.0 + 30.0, np.full(count, 80.0 + frame)])
    return CameraMessage(camera, frame, timestamp, frame, boxes, np.ones(count),
                         np.zeros(count, np.int64), colour.astype(np.int64))


def sequence(fps: float = 2.0, seconds: float = 10.0, seed: int = 0, offsets=(0.0, 0.0, 0.0),
             missing: dict | None = None):
    """Per frame: list of (timestamp, [messages]) instants; cameras may be offset in time."""
    rng = np.random.default_rng(seed)
    frames = np.arange(int(seconds * fps))
    instants = []
    for frame in frames:
        per_time: dict[float, list[CameraMessage]] = {}
        for camera, offset in zip(CAMERAS, offsets, strict=True):
            timestamp = frame / fps + offset
            points = walkers(np.array([timestamp]))[0]
            keep = [index for index in range(3)
                    if (missing or {}).get((int(frame), index)) is None]
            per_time.setdefault(timestamp, []).append(
                camera_message(camera, int(frame), timestamp, points[keep], rng))
        instants.extend(sorted(per_time.items()))
    return instants


def run(tracker, instants, flush: bool = True) -> Tracks:
    """Feed instants; with ``flush`` the stream ends there (the tracker fuses all it holds)."""
    parts = [tracker.update(timestamp, messages) for timestamp, messages in instants]
    if flush:
        parts.append(tracker.flush())
    return Tracks.concatenate(parts)


def identities(tracks: Tracks, times: np.ndarray) -> dict[int, set[int]]:
    """For each true walker, the set of track ids reported on it."""
    truth = walkers(tracks.timestamp)
    nearest = np.argmin(np.linalg.norm(truth - tracks.world_xy[:, None], axis=2), axis=1)
    return {walker: set(tracks.track_id[nearest == walker].tolist()) for walker in range(3)}


@pytest.mark.parametrize("fps", [2.0, 10.0])
def test_three_cameras_fuse_into_one_track_per_person(fps):
    tracker = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY)
    tracks = run(tracker, sequence(fps=fps))
    assert identities(tracks, tracks.timestamp) == {0: {1}, 1: {2}, 2: {3}}
    # One row per person and frame, not one per camera.
    assert len(tracks) == 3 * int(10 * fps)
    error = np.linalg.norm(tracks.world_xy - walkers(tracks.timestamp)[
        np.arange(len(tracks)), tracks.track_id - 1], axis=1)
    assert np.median(error) < 0.05


def test_a_missed_frame_keeps_the_identity():
    missing = {(frame, 1): True for frame in (6, 7)}  # walker 1 unseen by all for 1 s
    tracks = run(FusionTracker(PLANES, CAMERAS), sequence(missing=missing))
    assert identities(tracks, tracks.timestamp)[1] == {2}
    assert 6 not in tracks.frame[tracks.track_id == 2].tolist()


def test_cameras_with_offset_timestamps():
    instants = sequence(fps=2.0, offsets=(0.0, 0.04, 0.09))
    assert len(instants) == 3 * 20  # every camera's messages arrive at their own instant
    tracks = run(FusionTracker(PLANES, CAMERAS), instants)
    assert identities(tracks, tracks.timestamp) == {0: {1}, 1: {2}, 2: {3}}
    assert tracks.track_id.max() == 3


def test_state_round_trip_gives_the_same_output():
    instants = sequence(fps=5.0, seed=3, missing={(12, 0): True})
    uninterrupted = run(FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY), instants)
    first = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY)
    head = run(first, instants[:17], flush=False)
    resumed = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY)
    resumed.set_state(json.loads(json.dumps(first.get_state())))
    tail = run(resumed, instants[17:])
    joined = Tracks.concatenate([head, tail])
    np.testing.assert_array_equal(joined.track_id, uninterrupted.track_id)
    np.testing.assert_array_equal(joined.world_xy, uninterrupted.world_xy)
    np.testing.assert_array_equal(joined.frame, uninterrupted.frame)


def test_reset_restarts_identities():
    tracker = FusionTracker(PLANES, CAMERAS)
    instants = sequence(seconds=3.0)
    before = run(tracker, instants)
    tracker.reset()
    assert tracker.track_count == 0
    after = run(tracker, instants)
    np.testing.assert_array_equal(before.track_id, after.track_id)
    np.testing.assert_array_equal(before.world_xy, after.world_xy)


@pytest.mark.parametrize(
    "messages", [[], [CameraMessage.empty("north", 0, 0.0, 0)]], ids=["none", "empty"]
)
def test_empty_input(messages):
    tracker = FusionTracker(PLANES, CAMERAS)
    assert len(tracker.update(0.0, messages)) == 0
    assert tracker.track_count == 0


def test_a_single_camera_detection_is_not_reported_until_confirmed():
    rng = np.random.default_rng(0)
    tracker = FusionTracker(PLANES, CAMERAS)
    point = np.array([[1.0, 1.0]])
    first = tracker.update(0.0, [camera_message("north", 0, 0.0, point, rng)])
    # The other cameras might still send a message captured up to 0.25 s after 0.5 s:
    # the second view waits until the stream ends.
    second = tracker.update(0.5, [camera_message("north", 1, 0.5, point, rng)])
    assert len(first) == 0 and len(second) == 0 and tracker.waiting == 1
    last = tracker.flush()
    assert last.track_id.tolist() == [1] and last.camera_id.tolist() == [0]
    assert tracker.waiting == 0


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        ({"measurement_sigma_m": 0}, "measurement_sigma_m must be a positive number"),
        ({"gate_sigmas": -2}, "gate_sigmas must be a positive number"),
        ({"max_age_s": float("inf")}, "max_age_s must be a positive number"),
        ({"report_coasting_s": -1}, "report_coasting_s must be zero or a positive number"),
        ({"confirm_evidence": 0}, "confirm_evidence must be a whole number >= 1"),
        ({"confirm_evidence": 1.5}, "confirm_evidence must be a whole number >= 1"),
        ({"adapt_noise": "yes"}, "adapt_noise must be true or false"),
        ({"class_acceleration_sigma": {"tank": 2.0}}, "unknown class 'tank'"),
        ({"class_measurement_sigma_m": {"car": 0}}, "must be a positive number"),
        ({"camera_positions": {"west": (0, 0)}}, "camera_positions names unknown camera"),
        ({"camera_positions": {"north": (0, float("nan"))}},
         "must be finite (x, y) or (x, y, height) metres"),
        ({"camera_positions": {"north": (0, 1, 2, 3)}}, "must be finite (x, y) or (x, y, height)"),
        ({"camera_positions": {"north": (0, 1, -2)}},
         "camera height of 'north' must be above the ground, got -2 m"),
        ({"kalman": True}, "unknown option(s) for the fusion matcher: kalman"),
        ({"association_orders": 0}, "association_orders must be a whole number >= 1, got 0"),
        ({"association_orders": 2.5}, "association_orders must be a whole number >= 1"),
    ],
)
def test_bad_options(options, expected):
    with pytest.raises(MatcherError) as error:
        make_matcher("fusion", PLANES, CAMERAS, **options)
    assert expected in str(error.value)


def test_bad_state_and_unknown_camera():
    tracker = FusionTracker(PLANES, CAMERAS)
    with pytest.raises(MatcherError, match="not a saved fusion-tracker state"):
        tracker.set_state({})
    other = FusionTracker(PLANES, ["x"])
    with pytest.raises(MatcherError, match="saved state is for cameras"):
        tracker.set_state(other.get_state())
    with pytest.raises(MatcherError, match="unknown camera 'x'"):
        tracker.update(0.0, [CameraMessage.empty("x", 0, 0.0, 0)])


@pytest.mark.parametrize(
    ("points", "cameras", "expected"),
    [
        ([], [], []),
        ([(0, 0)], [0], [0]),
        ([(0, 0), (0.3, 0)], [0, 1], [0, 0]),  # two cameras, close: one object
        ([(0, 0), (0.3, 0)], [0, 0], [0, 1]),  # one camera sees two objects
        ([(0, 0), (3, 0)], [0, 1], [0, 1]),  # too far apart
        # complete linkage: a chain 0 -- 0.8 -- 1.6 is not one object within 1 m
        ([(0, 0), (0.8, 0), (1.6, 0)], [0, 1, 2], [0, 0, 1]),
    ],
)
def test_cluster_detections(points, cameras, expected):
    labels = cluster_detections(np.asarray(points, float).reshape(-1, 2),
                                np.asarray(cameras, np.int64), 0.2, 3.5)
    assert labels.tolist() == expected


@pytest.mark.parametrize("seed", range(40))
def test_clusters_are_complete_linkage_with_one_view_per_camera(seed):
    """Random crowds (dense enough that the greedy merge runs): every cluster holds one
    detection per camera and only compatible pairs, and no two clusters could still merge."""
    rng = np.random.default_rng(seed)
    count = int(rng.integers(10, 120))
    world_xy = rng.uniform(0, rng.uniform(1.0, 5.0), size=(count, 2))
    camera = rng.integers(0, int(rng.integers(2, 20)), count)
    sigma = rng.uniform(0.05, 0.4, count)
    labels = cluster_detections(world_xy, camera, sigma, 3.0)
    distance = np.linalg.norm(world_xy[:, None] - world_xy[None], axis=2)
    compatible = distance <= 3.0 * np.sqrt(sigma[:, None] ** 2 + sigma[None] ** 2)
    clusters = [np.flatnonzero(labels == label) for label in np.unique(labels)]
    for members in clusters:
        assert len(set(camera[members].tolist())) == len(members)
        assert compatible[np.ix_(members, members)].all()
    for index, one in enumerate(clusters):
        for other in clusters[index + 1:]:
            mergeable = (not set(camera[one].tolist()) & set(camera[other].tolist())
                         and compatible[np.ix_(one, other)].all())
            assert not mergeable


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


def test_noise_model_learns_the_disagreement_between_cameras():
    rng = np.random.default_rng(1)
    model = NoiseModel(0.2, 0.0)
    for _ in range(200):
        distance = rng.uniform(5, 30, size=(50, 2))
        sigma = 0.03 * distance  # 3 cm per metre
        truth = rng.uniform(0, 20, size=(50, 2))
        first = truth + rng.normal(size=(50, 2)) * sigma[:, :1]
        second = truth + rng.normal(size=(50, 2)) * sigma[:, 1:]
        model.learn(np.concatenate([first, second]), distance.T.reshape(-1),
                    np.tile(np.arange(50), 2))
    assert model.sigma_per_distance == pytest.approx(0.03, rel=0.15)
    assert model.sigma_m < 0.15  # from its prior of 0.2 m towards the true 0


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


def ray_pairs(rng, count, along_per_metre, lateral_m, bias_per_metre=0.0):
    """Two cameras' views of ``count`` objects: errors elongated along each camera's ray."""
    truth = rng.uniform(0, 20, size=(count, 2))
    cameras = rng.uniform(-20, 40, size=(2, count, 2))
    views, distances, directions = [], [], []
    for camera in cameras:
        offset = truth - camera
        distance = np.linalg.norm(offset, axis=1)
        direction = offset / distance[:, None]
        across = np.column_stack([-direction[:, 1], direction[:, 0]])
        along_error = rng.normal(size=count) * along_per_metre * distance
        along_error += bias_per_metre * distance
        lateral_error = rng.normal(size=count) * lateral_m
        views.append(truth + along_error[:, None] * direction + lateral_error[:, None] * across)
        distances.append(distance)
        directions.append(direction)
    return np.concatenate(views), np.concatenate(distances), np.concatenate(directions)


def test_noise_model_learns_the_error_along_and_across_the_ray():
    rng = np.random.default_rng(2)
    model = NoiseModel(0.2, 0.01)
    for _ in range(200):
        world_xy, distance, direction = ray_pairs(rng, 50, 0.04, 0.07)
        model.learn(world_xy, distance, np.tile(np.arange(50), 2), direction)
    assert model.sigma_per_distance == pytest.approx(0.04, rel=0.15)
    assert model.lateral_per_distance < 0.005
    along, lateral = model.variances(np.array([20.0]))
    assert np.sqrt(along[0]) == pytest.approx(0.8, rel=0.15)
    assert 0.05 < np.sqrt(lateral[0]) < 0.12  # truth 0.07, the prior (0.2 m) still pulls
    isotropic = NoiseModel(0.2, 0.01)  # the same pairs without their rays
    rng = np.random.default_rng(2)
    for _ in range(200):
        world_xy, distance, _ = ray_pairs(rng, 50, 0.04, 0.07)
        isotropic.learn(world_xy, distance, np.tile(np.arange(50), 2))
    assert isotropic.sigma_per_distance == pytest.approx(0.04 / np.sqrt(2), rel=0.2)
    assert model.bias(np.array([20.0]))[0] == pytest.approx(0.0, abs=0.02)


def test_noise_model_does_not_trust_the_small_axis_before_it_has_the_data():
    """Along-ray noise ten times the across-ray noise, learned from a prior 20x too small.

    Each pair is weighed by its own predicted covariance, so the large along-ray residuals
    do not leak into the small across-ray coefficients: the across-ray estimate comes down
    to the truth from above instead of collapsing below it (an over-confident camera would
    pull tracks hard across its ray on a wrong association).
    """
    rng = np.random.default_rng(5)
    model = NoiseModel(0.2, 0.01, 0.01)
    lateral_history = []
    for _ in range(30):  # 30 instants of 100 objects seen by two cameras
        world_xy, distance, direction = ray_pairs(rng, 100, 0.04, 0.07)
        model.learn(world_xy, distance, np.tile(np.arange(100), 2), direction)
        along, lateral = model.variances(np.array([20.0]))
        lateral_history.append(float(np.sqrt(lateral[0])))
    assert min(lateral_history) > 0.06  # truth 0.07 m at every distance
    assert lateral_history[-1] == pytest.approx(0.07, rel=0.2)
    assert np.sqrt(along[0]) == pytest.approx(0.8, rel=0.1)  # truth 0.04 x 20 m


def test_inverse_cholesky_whitens_like_numpy():
    rng = np.random.default_rng(4)
    factor = rng.normal(size=(50, 2, 2))
    covariance = factor @ np.swapaxes(factor, 1, 2) + 0.01 * np.eye(2)
    whitening = inverse_cholesky_2x2(covariance)
    assert whitening == pytest.approx(np.linalg.inv(np.linalg.cholesky(covariance)))
    # Whitened, each covariance is the identity.
    identity = whitening @ covariance @ np.swapaxes(whitening, 1, 2)
    assert identity == pytest.approx(np.broadcast_to(np.eye(2), identity.shape))


def test_noise_model_learns_a_bias_along_the_ray():
    rng = np.random.default_rng(3)
    model = NoiseModel(0.2, 0.01)
    for _ in range(100):
        world_xy, distance, direction = ray_pairs(rng, 50, 0.01, 0.05, bias_per_metre=0.01)
        model.learn(world_xy, distance, np.tile(np.arange(50), 2), direction)
    assert model.bias_per_distance == pytest.approx(0.01, rel=0.1)
    # The bias is removed before the noise is fitted: it does not inflate the noise.
    assert model.sigma_per_distance == pytest.approx(0.01, rel=0.2)


@pytest.mark.parametrize("along, lateral", [(1.0, 0.01), (0.04, 0.04)])
def test_fusing_two_crossing_rays(along, lateral):
    """Two views along x and along y: each pins the other's long axis."""
    direction = np.array([[1.0, 0.0], [0.0, 1.0]])
    covariance = ray_covariance(direction, np.full(2, along), np.full(2, lateral))
    world_xy = np.array([[1.0, 0.0], [0.0, 1.0]])
    position, fused, present = fuse(np.array([0, 0]), 2, world_xy, covariance)
    weight_x = (1 / along) / (1 / along + 1 / lateral)  # view 0 is long along x
    assert position[0] == pytest.approx([weight_x, weight_x])  # each axis trusts its precise view
    expected = 1.0 / (1 / along + 1 / lateral)
    assert fused[0] == pytest.approx(np.diag([expected, expected]))
    assert present.tolist() == [True, False] and np.isnan(position[1]).all()


def test_kalman_update_with_isotropic_matrices_matches_variances():
    state = np.array([[0.0, 0.0, 1.0, 0.0], [2.0, 1.0, 0.0, -1.0]])
    covariance = kalman.initial_covariance(2, np.array([0.3, 0.5]), 1.5)
    measured = np.array([[0.2, -0.1], [2.5, 0.8]])
    variance = np.array([0.04, 0.09])
    by_variance = kalman.update(state, covariance, measured, variance)
    by_matrix = kalman.update(state, covariance, measured, variance[:, None, None] * np.eye(2))
    for one, other in zip(by_variance, by_matrix, strict=True):
        assert one == pytest.approx(other)
    # Covariance (2, 2) at birth: kept as given.
    matrix = np.array([[[0.5, 0.1], [0.1, 0.2]]])
    assert kalman.initial_covariance(1, matrix, 1.0)[0, :2, :2] == pytest.approx(matrix[0])


def test_low_cameras_see_more_along_ray_noise():
    """With heights, the along-ray distance scales by mean height / camera height."""
    positions = {"north": (5.0, 22.0, 2.0), "east": (22.0, 5.0, 8.0), "south": (5.0, -12.0, 4.0)}
    tracker = FusionTracker(PLANES, CAMERAS, camera_positions=positions)
    assert tracker._along_scale == pytest.approx([2.0, 0.5, 1.0])
    flat = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY)
    assert flat._along_scale == pytest.approx([1.0, 1.0, 1.0])
    tracks = run(tracker, sequence())
    assert identities(tracks, tracks.timestamp) == {0: {1}, 1: {2}, 2: {3}}


def test_one_motion_model_is_a_plain_kalman_filter():
    rng = np.random.default_rng(4)
    state = rng.normal(size=(3, 4))
    covariance = kalman.initial_covariance(3, np.array([0.1, 0.2, 0.3]), 1.0)
    sigma = np.array([0.5, 1.0, 2.0])
    plain = kalman.predict(state, covariance, 0.5, sigma)
    models = kalman.predict_models(state[:, None], covariance[:, None], np.ones((3, 1)), 0.5,
                                   sigma[:, None], np.array([3.0]))
    assert models[0][:, 0] == pytest.approx(plain[0])
    assert models[1][:, 0] == pytest.approx(plain[1])
    measured = rng.normal(size=(3, 2))
    plain = kalman.update(*plain, measured, np.full(3, 0.04))
    updated = kalman.update_models(*models, measured, np.full(3, 0.04))
    assert updated[0][:, 0] == pytest.approx(plain[0])
    assert updated[2] == pytest.approx(np.ones((3, 1)))


def test_a_turn_shifts_weight_to_the_manoeuvring_model():
    """Walk straight, then turn 90 degrees: the agile model gains, then the steady one."""
    sojourn = np.array([10.0, 2.0])
    probability = kalman.stationary_probability(sojourn)[None]
    assert probability[0] == pytest.approx([10 / 12, 2 / 12])
    state = np.zeros((1, 2, 4))
    covariance = np.repeat(kalman.initial_covariance(1, 0.01, 1.5)[:, None], 2, axis=1)
    sigma = np.array([[0.5, 2.0]])
    history = []
    for step in range(1, 41):
        time = 0.5 * step
        truth = (1.3 * time, 0.0) if time <= 10 else (13.0, 1.3 * (time - 10))
        state, covariance, probability = kalman.predict_models(
            state, covariance, probability, 0.5, sigma, sojourn)
        state, covariance, probability = kalman.update_models(
            state, covariance, probability, np.array([truth]), np.array([0.01]))
        history.append(probability[0, 1])
    before, turn, after = history[15], max(history[19:24]), history[-1]
    assert before < 0.2 and turn > 0.5 and after < 0.2
    combined_state, _ = kalman.combine(state, covariance, probability)
    assert combined_state[0, 2:] == pytest.approx([0.0, 1.3], abs=0.1)


def test_motion_model_options_are_checked():
    with pytest.raises(MatcherError, match="one entry per model, got 2 and 1"):
        FusionTracker(PLANES, CAMERAS, model_sojourn_s=(5.0,))
    with pytest.raises(MatcherError, match="model_acceleration_factors must be a non-empty"):
        FusionTracker(PLANES, CAMERAS, model_acceleration_factors=())


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
            tracker.config = dataclasses.replace(tracker.config, association_orders=orders)
            assigned = tracker._associate(observed, covariance)
            track_cost, detection_cost = tracker._joint_cost(
                observed, covariance, assigned, list(range(len(CAMERAS)))
            )
            costs[orders] = track_cost.sum() + detection_cost.sum()
        assert costs[3] <= costs[1] + 1e-6
        improved += costs[3] < costs[1] - 1e-6
        tracker.update(timestamp, messages)
    assert improved > 0  # the scene is crowded enough for the orders to disagree
