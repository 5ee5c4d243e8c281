"""The fusion tracker on synthetic messages: fusion across cameras, gaps, timing, state."""

from __future__ import annotations

import numpy as np
import pytest
from fusion_scenes import (
    CAMERA_XY,
    CAMERAS,
    PLANES,
    camera_message,
    identities,
    run,
    sequence,
    walkers,
)

from cblrs.detections import CameraMessage
from cblrs.matching import FusionTracker, kalman


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


