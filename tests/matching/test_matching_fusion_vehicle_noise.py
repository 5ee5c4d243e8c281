"""Fusion tracker: where a vehicle refined by its heading is reported
(:mod:`cblrs.matching.fusion.vehicle_noise`), and a new track's class-scaled velocity
uncertainty (:class:`~cblrs.matching.fusion.table.FusionContext`)."""

from __future__ import annotations

import math

import numpy as np

from cblrs.camera import Camera
from cblrs.datasets.synthetic import MovingObject, SyntheticWorld, WaypointPath, WorldSpec
from cblrs.detections import CLASS_NAMES
from cblrs.matching.base import Observations
from cblrs.matching.fusion import vehicle_noise as module
from cblrs.matching.fusion.birth import Births
from cblrs.matching.fusion.config import FusionConfig
from cblrs.matching.fusion.noise import NoiseModel
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable
from cblrs.matching.fusion.vehicle_noise import VehicleNoise
from cblrs.pipeline import render_scene_references, track_scene

CAR = CLASS_NAMES.index("car")
PERSON = CLASS_NAMES.index("person")


def _context(config: FusionConfig | None = None) -> FusionContext:
    config = config or FusionConfig()
    extra = np.array([config.class_measurement_sigma_m.get(name, 0.0) for name in CLASS_NAMES]
                     + [0.0])
    return FusionContext(config, ["a", "b"], np.array([[0.0, 0.0], [20.0, 0.0]]), extra,
                         np.ones(len(extra)), NoiseModel(0.2, 0.01))


def _tracks(classes, heading_known) -> TrackTable:
    count = len(classes)
    return TrackTable(
        ids=np.arange(count), class_id=np.asarray(classes, np.int64),
        state=np.tile([10.0, 10.0, 5.0, 0.0], (count, 1)),
        covariance=np.tile(np.diag([0.5, 0.5, 1.0, 1.0]), (count, 1, 1)),
        mode_state=np.zeros((count, 2, 4)), mode_covariance=np.zeros((count, 2, 4, 4)),
        mode_probability=np.full((count, 2), 0.5), evidence=np.ones(count, np.int64),
        last_seen=np.zeros(count), seen_by=np.zeros((count, 2)),
        velocity_sigma=np.ones(count),
        heading=np.where(np.asarray(heading_known)[:, None], [[1.0, 0.0]], [[0.0, 0.0]]),
        heading_time=np.where(heading_known, 0.0, -np.inf), heading_sigma=np.zeros(count),
    )


def _measured(world_xy: np.ndarray, camera: np.ndarray) -> Measured:
    offset = world_xy - np.array([[0.0, 0.0], [20.0, 0.0]])[camera]
    distance = np.hypot(offset[:, 0], offset[:, 1])
    return Measured(distance, distance, offset / distance[:, None], np.full(len(camera), 0.3))


def test_only_vehicles_of_tracks_with_a_known_heading_are_refined():
    noise = VehicleNoise(_context())
    tracks = _tracks([CAR, CAR, PERSON], [True, False, True])
    class_id = np.array([CAR, CAR, CAR, PERSON, CAR])
    assigned = np.array([0, 0, 1, 2, -1])
    assert noise.refined(tracks, class_id, assigned).tolist() == [
        True, True, False, False, False]
    assert not VehicleNoise(_context(), enabled=False).refined(
        tracks, class_id, assigned).any()


def test_a_refined_track_is_reported_where_its_views_are_not_where_it_was_predicted():
    noise = VehicleNoise(_context())
    tracks = _tracks([CAR, CAR], [True, True])
    truth = np.array([10.6, 10.2])  # the prediction (10, 10) lags 0.6 m and drifts 0.2 m
    world_xy = truth + np.array([[0.03, -0.02], [-0.02, 0.03]])
    camera = np.array([0, 1])
    assigned = np.array([0, 0])
    refined = noise.refined(tracks, np.array([CAR, CAR]), assigned)
    located = noise.locate(tracks, world_xy, _measured(world_xy, camera), refined,
                           np.zeros((2, 2, 2)), assigned, np.array([CAR, CAR]), 0.0)
    assert np.isnan(located[1]).all()  # no refined views: the filter's estimate
    assert np.hypot(*(located[0] - truth)) < 0.15
    # Reported only at the instant it was located; coasting tracks report the filter.
    tracks.located = located
    tracks.last_seen = np.array([0.0, 0.0])
    assert np.allclose(noise.position(tracks, np.array([0, 1]), 0.0),
                       [located[0], tracks.state[1, :2]])
    assert np.allclose(noise.position(tracks, np.array([0]), 0.1), tracks.state[:1, :2])


def test_the_noise_is_learned_from_the_refined_views_and_saved():
    noise = VehicleNoise(_context())
    rng = np.random.default_rng(0)
    prior = noise.model.sigma_m
    for _ in range(200):
        truth = rng.uniform(5.0, 15.0, (10, 2))
        world_xy = np.repeat(truth, 2, axis=0) + rng.normal(0.0, 0.05, (20, 2))
        camera = np.tile([0, 1], 10)
        noise.learn(world_xy, _measured(world_xy, camera), np.ones(20, bool),
                    np.repeat(np.arange(10), 2), np.full(20, CAR))
    assert noise.model.sigma_m < 0.5 * prior
    # Each class apart: a bus's noise is not a car's.
    assert noise.models[CLASS_NAMES.index("bus")].sigma_m == prior
    restored = VehicleNoise(_context())
    restored.set_state(noise.get_state())
    assert restored.model.sigma_m == noise.model.sigma_m
    restored.set_state(None)  # a state saved before this stage
    assert restored.model.sigma_m == prior


def test_a_new_track_velocity_is_as_uncertain_as_its_class_drives():
    context = _context()
    assert context.class_velocity_sigma[PERSON] == FusionConfig().initial_velocity_sigma
    assert context.class_velocity_sigma[CAR] > 4 * context.class_velocity_sigma[PERSON]
    leftovers = Observations(
        world_xy=np.array([[0.0, 0.0], [30.0, 0.0]]), colour=np.zeros((2, 3), np.int64),
        camera=np.array([0, 0]), xyxy=np.zeros((2, 4)), confidence=np.ones(2),
        class_id=np.array([PERSON, CAR]))
    born = Births(context).birth(leftovers, np.tile(0.04 * np.eye(2), (2, 1, 1)), 0.0).tracks
    sigma = np.sqrt(born.covariance[:, 2, 2])
    assert np.allclose(sigma[born.class_id == PERSON], context.class_velocity_sigma[PERSON])
    assert np.allclose(sigma[born.class_id == CAR], context.class_velocity_sigma[CAR])


def _ring_world() -> WorldSpec:
    # One car twice round a 12 m ring at 8 m/s (it turns all the time), three cameras.
    cameras = tuple(
        Camera.from_pose(
            name, (x, y, 10.0), math.degrees(math.atan2(-y, -x)), 20.0, 700.0, (1280, 720)
        )
        for name, x, y in (("NE", 25.0, 25.0), ("SW", -25.0, -25.0), ("SE", 25.0, -25.0))
    )
    angles = np.linspace(0.0, 4.0 * np.pi, 97)
    ring = tuple((12.0 * math.cos(a), 12.0 * math.sin(a)) for a in angles)
    car = MovingObject(1, "car", (4.5, 1.8, 1.5), WaypointPath(ring, 8.0, 0.0))
    return WorldSpec(name="ring", cameras=cameras, objects=(car,),
                     area=(-30.0, -30.0, 30.0, 30.0), duration_s=8.0, fps=10.0)


def test_a_car_on_a_ring_is_reported_nearer_its_centre(monkeypatch):
    scene = SyntheticWorld(_ring_world()).scene()
    references = render_scene_references(scene)
    truth = scene.ground_truth

    def mean_error(tracks) -> float:
        errors = []
        for frame, xy in zip(tracks.frame, tracks.world_xy, strict=True):
            errors.append(np.hypot(*(truth.world_xy[truth.frame == frame][0] - xy)))
        return float(np.mean(errors))

    located = track_scene(scene, references=references).tracks
    monkeypatch.setattr(module.VehicleNoise, "position",
                        staticmethod(lambda tracks, rows, timestamp: tracks.state[rows, :2]))
    filtered = track_scene(scene, references=references).tracks
    assert len(np.unique(located.track_id)) == 1
    assert np.array_equal(located.track_id, filtered.track_id)  # association unchanged
    assert mean_error(located) < 0.2
    assert mean_error(located) < 0.7 * mean_error(filtered)


def _located_after_sharp_learning(vehicle_floor: float) -> np.ndarray:
    """Where a settled truck track predicted at (10, 10) is reported from two views that
    agree within centimetres at (10.6, 10.2), after the noise learned cameras agreeing
    within 2 cm."""
    noise = VehicleNoise(_context(FusionConfig(vehicle_minimum_sigma_m=vehicle_floor)))
    truck = CLASS_NAMES.index("truck")
    rng = np.random.default_rng(1)
    for _ in range(200):
        truth = rng.uniform(5.0, 15.0, (10, 2))
        world_xy = np.repeat(truth, 2, axis=0) + rng.normal(0.0, 0.02, (20, 2))
        camera = np.tile([0, 1], 10)
        noise.learn(world_xy, _measured(world_xy, camera), np.ones(20, bool),
                    np.repeat(np.arange(10), 2), np.full(20, truck))
    tracks = _tracks([truck], [True])
    tracks.covariance[:] = np.diag([0.05, 0.05, 1.0, 1.0])
    world_xy = np.array([[10.61, 10.2], [10.59, 10.2]])
    assigned = np.array([0, 0])
    refined = noise.refined(tracks, np.array([truck, truck]), assigned)
    return noise.locate(tracks, world_xy, _measured(world_xy, np.array([0, 1])), refined,
                        np.zeros((2, 2, 2)), assigned, np.array([truck, truck]), 0.0)[0]


def test_closely_agreeing_views_of_a_vehicle_are_trusted_no_more_than_its_floor():
    # Cameras that agree within centimetres still share the footprint's error of a
    # class-typical size: one instant's views move a settled track part of the way.
    floored = _located_after_sharp_learning(0.3)
    unfloored = _located_after_sharp_learning(0.0)  # 0: the shared minimum_sigma_m
    assert 0.2 < floored[0] - 10.0 < 0.4  # gain 0.05 / (0.05 + 0.3^2 / 2 + 0.1^2) = 0.48
    assert unfloored[0] - 10.0 > 0.45  # gain 0.05 / (0.05 + 0.05^2 / 2 + 0.1^2) = 0.82
