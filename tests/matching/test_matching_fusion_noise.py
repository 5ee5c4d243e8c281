"""Fusion tracker: the learned measurement-noise model (:mod:`cblrs.matching.fusion.noise`)."""

from __future__ import annotations

import numpy as np
import pytest
from fusion_scenes import (
    CAMERA_XY,
    CAMERAS,
    PLANES,
    identities,
    run,
    sequence,
)

from cblrs.matching import FusionTracker
from cblrs.matching.fusion import (
    NoiseModel,
)


def ray_pairs(rng, count, along_per_metre, lateral_m, bias_per_metre=0.0, constant_m=0.0):
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
        along_error += bias_per_metre * distance + constant_m
        lateral_error = rng.normal(size=count) * lateral_m
        views.append(truth + along_error[:, None] * direction + lateral_error[:, None] * across)
        distances.append(distance)
        directions.append(direction)
    return np.concatenate(views), np.concatenate(distances), np.concatenate(directions)


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


def test_noise_model_learns_a_bias_along_the_ray():
    rng = np.random.default_rng(3)
    model = NoiseModel(0.2, 0.01)
    for _ in range(100):
        world_xy, distance, direction = ray_pairs(rng, 50, 0.01, 0.05, bias_per_metre=0.01)
        model.learn(world_xy, distance, np.tile(np.arange(50), 2), direction)
    assert model.bias_per_distance == pytest.approx(0.01, rel=0.1)
    # The bias is removed before the noise is fitted: it does not inflate the noise.
    assert model.sigma_per_distance == pytest.approx(0.01, rel=0.2)


@pytest.mark.parametrize("constant_bias", [True, False])
def test_a_foot_point_short_of_the_centre_is_learnt_as_a_constant_bias(constant_bias):
    """A box's bottom is the near edge of a body: 0.25 m short of its centre at any distance."""
    rng = np.random.default_rng(4)
    model = NoiseModel(0.2, 0.01, constant_bias=constant_bias)
    for _ in range(100):
        world_xy, distance, direction = ray_pairs(rng, 50, 0.002, 0.03, constant_m=-0.25)
        model.learn(world_xy, distance, np.tile(np.arange(50), 2), direction)
    if constant_bias:
        assert model.bias_constant_m == pytest.approx(-0.25, abs=0.02)
        assert model.bias(np.array([5.0, 30.0])) == pytest.approx([-0.25, -0.25], abs=0.03)
    else:  # the proportional bias alone: a compromise, wrong near and far
        assert model.bias_constant_m == 0.0
        near, far = model.bias(np.array([5.0, 30.0]))
        assert abs(near - far) > 0.1


@pytest.mark.parametrize("bias_per_metre", [0.0, 0.01])
def test_no_constant_bias_where_the_views_have_none(bias_per_metre):
    """Noise with no offset, or a bias proportional to distance: the constant stays 0 and
    the proportional bias is what the model without it learns."""
    results = []
    for constant_bias in (True, False):
        rng = np.random.default_rng(3)
        model = NoiseModel(0.2, 0.01, constant_bias=constant_bias)
        for _ in range(100):
            world_xy, distance, direction = ray_pairs(rng, 50, 0.02, 0.05,
                                                      bias_per_metre=bias_per_metre)
            model.learn(world_xy, distance, np.tile(np.arange(50), 2), direction)
        results.append((model.bias_constant_m, model.bias_per_distance))
    assert results[0] == results[1]
    assert results[0][0] == 0.0


def test_the_constant_bias_is_saved_and_restored():
    rng = np.random.default_rng(4)
    model = NoiseModel(0.2, 0.01, constant_bias=True)
    for _ in range(20):
        world_xy, distance, direction = ray_pairs(rng, 50, 0.002, 0.03, constant_m=-0.25)
        model.learn(world_xy, distance, np.tile(np.arange(50), 2), direction)
    restored = NoiseModel(0.2, 0.01, constant_bias=True)
    restored.set_state(model.get_state())
    assert restored.bias_constant_m == model.bias_constant_m < 0
    world_xy, distance, direction = ray_pairs(rng, 50, 0.002, 0.03, constant_m=-0.25)
    for one in (model, restored):
        one.learn(world_xy, distance, np.tile(np.arange(50), 2), direction)
    assert restored.bias_constant_m == model.bias_constant_m


def test_low_cameras_see_more_along_ray_noise():
    """With heights, the along-ray distance scales by mean height / camera height."""
    positions = {"north": (5.0, 22.0, 2.0), "east": (22.0, 5.0, 8.0), "south": (5.0, -12.0, 4.0)}
    tracker = FusionTracker(PLANES, CAMERAS, camera_positions=positions)
    assert tracker._along_scale == pytest.approx([2.0, 0.5, 1.0])
    flat = FusionTracker(PLANES, CAMERAS, camera_positions=CAMERA_XY)
    assert flat._along_scale == pytest.approx([1.0, 1.0, 1.0])
    tracks = run(tracker, sequence())
    assert identities(tracks, tracks.timestamp) == {0: {1}, 1: {2}, 2: {3}}

